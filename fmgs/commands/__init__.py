"""The ``fmgs`` subcommands, one module each (nerfstudio's layout): ``add_parser(sub)`` registers the
command, its flags and help on the ``fmgs`` parser, and ``run(args)`` runs it. ``fmgs.cli`` assembles them
in ``COMMANDS`` order. The modules import only argparse and the light config modules at the top; the
library (torch) is imported inside ``run``, so ``fmgs --help`` stays fast."""

COMMANDS = (
    "info",
    "render",
    "synth",
    "sfm",
    "train_gs",
    "eval_gs",
    "features",
    "train_field",
    "build",
    "bag_info",
    "shard",
    "serve",
)
"""The command modules (``fmgs.commands.NAME``), in the order ``fmgs --help`` lists them."""
