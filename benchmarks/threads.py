"""Training speed against CPU thread count: short train-gs runs on a synthetic scene, alternating settings.

Each run is its own process (torch and numba pools start fresh), trains ``--steps`` steps of the reduced
3000-step schedule with ``GSTrainConfig.threads`` set to 1, 2, or left to torch's and numba's own default
(every core), in turn, ``--repeats`` times; reports the median steps/s of each and the load average seen.
Writes benchmarks/results/THREADS.md and THREADS.json.

    python -m benchmarks.threads [--steps 100] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import RESULTS

# One run: "default" leaves both pools as they start (what train-gs did before GSTrainConfig.threads).
RUN = """
import json, sys, time, torch, numba
from dataclasses import replace
from fmgs.data.dataset import load_dataset
from fmgs.train.config import GSTrainConfig
from fmgs.train import gaussians as G
data, out, steps, setting = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
if setting == "default":
    G.thread_count = lambda n: __import__("contextlib").nullcontext(torch.get_num_threads())
cfg = replace(GSTrainConfig.reduced(3000), steps=steps, threads=0 if setting == "default" else int(setting))
r = G.train_gaussians(load_dataset(data), out, cfg, progress=False, resume=False)
rec = json.load(open(out + "/train.json"))["threads"]
print(json.dumps({"steps_per_s": steps / r.seconds, "torch": torch.get_num_threads(),
                  "numba": numba.get_num_threads(), "recorded": rec}))
"""
SETTINGS = ("1", "2", "default")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS / "THREADS.md"))
    args = ap.parse_args(argv)
    from fmgs.synth import SynthConfig, generate

    work = Path(tempfile.mkdtemp(prefix="fmgs-threads-"))
    runs: dict[str, list[float]] = {s: [] for s in SETTINGS}
    loads = []
    try:
        generate(work / "scene", SynthConfig(views=32, width=128, height=96))
        for rep in range(args.repeats):
            for setting in SETTINGS:
                loads.append(os.getloadavg()[0])
                cmd = [sys.executable, "-c", RUN, str(work / "scene"), str(work / "run"), str(args.steps)]
                p = subprocess.run(
                    [*cmd, setting],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                r = json.loads(p.stdout.strip().splitlines()[-1])
                runs[setting].append(r["steps_per_s"])
                print(rep, setting, r, f"load {loads[-1]:.2f}", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    med = {s: statistics.median(v) for s, v in runs.items()}
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps({"runs": runs, "median": med, "loads": loads}, indent=1))
    cpu = platform.processor() or platform.machine()
    lines = [
        "# Training speed against CPU threads",
        "",
        f"`python -m benchmarks.threads --steps {args.steps} --repeats {args.repeats}` on {cpu} "
        f"({os.cpu_count()} cores, {platform.node()}), CPU backend, synthetic scene 32 views 128x96. "
        "Each run is a fresh process training the first steps of `GSTrainConfig.reduced(3000)`; the settings "
        "alternate. 1-minute load average before the runs: "
        f"{min(loads):.2f}-{max(loads):.2f} (other jobs share the machine).",
        "",
        "| threads | median steps/s | runs |",
        "|---|---:|---|",
    ]
    lines += [f"| {s} | {med[s]:.2f} | " + ", ".join(f"{x:.2f}" for x in runs[s]) + " |" for s in SETTINGS]
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
