"""Presence rules side by side on built scenes: how the query's best Gaussians decide ``found``.

    python -m benchmarks.presence_rules --out OUT --seeds 301,302 --variants labels,dominant [--report]

OUT is a ``benchmarks.clip_path`` folder (OUT/scene-SEED, OUT/models/sSEED and sSEED-VARIANT): every
package is opened as the server opens it and asked the presence queries of benchmarks.unseen (names,
paraphrases, absent objects, colour swaps, unrelated things) under each rule of ``RULES``; nothing is
built. The served rule was chosen on seeds 301-302 (not scored by any other report) with this script.
Writes OUT/presence_rules.json and OUT/PRESENCE_RULES.md (``--report``: benchmarks/results/ too).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from benchmarks.common import machine, machine_words, save_report
from fmgs.query.presence import PresenceConfig

RULES = {
    "best (each, quorum 1)": PresenceConfig(rule="each"),
    "quorum 10 (each)": PresenceConfig(rule="each", quorum=10),
    "mean of 5": PresenceConfig(pool=5),
    "mean of 10": PresenceConfig(pool=10),
    "mean of 64": PresenceConfig(pool=64),
}
"""Fixed before the measurement: the rule served before, a quorum of an instance's worth, and the mean of
half, one and six instances' worth of the best Gaussians."""


def score_package(out: Path, seed: int, variant: str) -> dict:
    """Per rule: (present found, present, absent rejected, absent) of one package, and the rows."""
    from benchmarks.clip_path import presence_accuracy, variant_name
    from benchmarks.unseen import score_presence
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine

    name = f"s{seed}" if variant == "labels" else variant_name(seed, variant)
    engine = SceneEngine.open(out / "models" / name)
    names = json.loads((out / f"scene-{seed}" / "scene.json").read_text())["label_names"]
    enc = MiniLMTextEncoder()
    rows = {rule: score_presence(engine, enc, names, cfg) for rule, cfg in RULES.items()}
    return {rule: {"counts": presence_accuracy({"p": r}, "p"), "rows": r} for rule, r in rows.items()}


def report(d: dict) -> str:
    info = d["machine"]
    lines = [
        "# Presence rules side by side",
        "",
        f"Measured {info['date']} on {machine_words(info)}, one run of `{d['command']}`. Scenes of "
        "`benchmarks.clip_path` (the wider world, 10 objects, 3 with held-out names) on seeds no other "
        "report scores, built with label targets and with CLIP targets through the stand-ins at the "
        "build's defaults; every package asked the presence queries of `benchmarks.unseen` under each "
        "rule (`fmgs.query.presence.PresenceConfig`): *best*, the single best of the query's 64 best "
        "Gaussians must be closer to the query than to every negative it does not mean (the rule served "
        "before); *quorum 10*, the 10th best must; *mean of P*, the mean embedding of the P best must. "
        "Builds: `python -m benchmarks.clip_path --out OUT --seeds "
        + ",".join(map(str, d["seeds"]))
        + " --variants dominant --target-views 1`.",
        "",
        "| targets | scenes | " + " | ".join(RULES) + " |",
        "|---|---:|" + "---:|" * len(RULES),
    ]
    for v in d["variants"]:
        lines.append(f"| {v} | {len(d['scenes'])} | " + " | ".join(_cells(d["scenes"], v)) + " |")
    if len(d["scenes"]) > 1:
        lines += ["", "Per scene:", "", "| seed | targets | " + " | ".join(RULES) + " |",
                  "|---:|---|" + "---:|" * len(RULES)]  # fmt: skip
        for seed, scene in zip(d["seeds"], d["scenes"], strict=True):
            for v in d["variants"]:
                lines.append(f"| {seed} | {v} | " + " | ".join(_cells([scene], v)) + " |")
    return "\n".join([*lines, ""])


def _cells(scenes: list[dict], variant: str) -> list[str]:
    """Per rule: presence pooled over ``scenes`` with its counts, as the report's cells."""
    cells = []
    for rule in RULES:
        f, p, a, n = (sum(x) for x in zip(*(s[variant][rule]["counts"] for s in scenes), strict=True))
        cells.append(f"{(f + a) / max(p + n, 1):.3f} ({f}/{p} found, {a}/{n} rejected)")
    return cells


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="a benchmarks.clip_path folder")
    ap.add_argument("--seeds", default="301,302")
    ap.add_argument("--variants", default="labels,dominant")
    ap.add_argument("--report", action="store_true", help="also write benchmarks/results/PRESENCE_RULES.md")
    a = ap.parse_args()
    out = Path(a.out)
    variants = [v for v in a.variants.split(",") if v]
    scenes = [{v: score_package(out, int(s), v) for v in variants} for s in a.seeds.split(",")]
    d = {
        "command": "python -m benchmarks.presence_rules " + " ".join(sys.argv[1:]),
        "machine": {**machine(), "date": time.strftime("%Y-%m-%d")},
        "seeds": [int(s) for s in a.seeds.split(",")],
        "variants": variants,
        "scenes": scenes,
    }
    text = report(d)
    (out / "presence_rules.json").write_text(json.dumps(d, indent=1, default=float))
    save_report(text, out, "PRESENCE_RULES.md", a.report)
    if a.report:
        save_report(json.dumps(d, indent=1, default=float), out, "PRESENCE_RULES.json", True)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
