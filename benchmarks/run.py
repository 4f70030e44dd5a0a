"""Work-precision report: the error every speed knob costs against the time it saves, scaling, floors.

    python -m benchmarks.run                  # full size -> benchmarks/results/REPORT.md and report/
    python -m benchmarks.run --quick          # CI size -> a temporary folder (or --out DIR)
    python -m benchmarks.run --only text,pose # some sections, merged into the results already in --out

Sections: ``text`` (per-Gaussian text query), ``pose`` (relevancy image), ``field`` (feature-field
training), ``gs`` (3DGS training), ``scaling`` (latency and memory against size, gRPC against
concurrency), ``floor`` (this machine's bandwidth and arithmetic rate, and each hot path's time as a
multiple of the floor they imply), ``targets`` (CLIP target blends: object pixels named right before
distillation against target time per view). Every work-precision diagram puts the error on one axis and
the run time on the other, one curve per knob, with the exact reference as a point; that point is the
exact path re-run inside the timing loop and compared with the reference like every other setting, so its
error is measured, not assumed. The default point of the text and pose diagrams is the product path
(SceneEngine on an exported scene package, opened as the query server opens it). The exit status is 1
when any exact point shows a non-zero error.

Outputs (each stamped with machine, versions, date and commit): REPORT.md, one PNG per diagram,
results.json (everything) and one CSV per table.

The code lives in benchmarks/workprec/: sizes.py (quick and full sizes), measure.py (error measures,
timing, growth fits, cost models), engine.py (the product path), one module per section (text.py,
pose.py, gs.py, field.py, scaling.py, floor.py, targets.py: its measurement, table, reading and plot),
plots.py and report.py (CSV, PNG, REPORT.md). This file is the command line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from benchmarks.common import RESULTS
from benchmarks.workprec import field, floor, gs, pose, scaling, targets, text
from benchmarks.workprec.measure import exact_failures, set_threads
from benchmarks.workprec.report import SECTIONS, machine_info, write_report
from benchmarks.workprec.sizes import FULL, QUICK, Sizes


def run_section(name: str, sizes: Sizes, work: Path, threads: int) -> dict:
    """Measure one section; ``work`` holds its intermediate scenes, packages and fits."""
    if name == "text":
        return text.section(sizes.text, work)
    if name == "pose":
        return pose.section(sizes.pose, work)
    if name == "gs":
        return gs.section(sizes.gs, sizes.scene, work)
    if name == "field":
        return field.section(sizes.field, sizes.scene, work)
    if name == "scaling":
        return scaling.section(sizes.scaling, work, threads)
    if name == "floor":
        return floor.section(sizes.floor, threads)
    if name == "targets":
        return targets.section(sizes.targets, work)
    raise ValueError(name)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="CI size (about 2 minutes)")
    ap.add_argument("--only", default=",".join(SECTIONS), help=f"comma-separated sections of {SECTIONS}")
    ap.add_argument(
        "--out", type=Path, help="output folder (full default: benchmarks/results/report; quick: a temp dir)"
    )
    ap.add_argument("--work", type=Path, help="keep intermediate scenes and fits here (default: a temp dir)")
    ap.add_argument(
        "--threads", type=int, default=1, help="threads for queries, renders, training (default 1)"
    )
    ap.add_argument(
        "--report-only", action="store_true", help="rewrite the report, plots and CSV from OUT/results.json"
    )
    a = ap.parse_args(argv)
    only = [s.strip() for s in a.only.split(",") if s.strip()]
    bad = [s for s in only if s not in SECTIONS]
    if bad:
        ap.error(f"unknown sections {bad}; choose from {SECTIONS}")
    sizes = QUICK if a.quick else FULL
    default_out = a.out is None
    out = a.out or (Path(tempfile.mkdtemp(prefix="fmgs-bench-")) if a.quick else RESULTS / "report")
    report = RESULTS / "REPORT.md" if default_out and not a.quick else out / "REPORT.md"
    out.mkdir(parents=True, exist_ok=True)
    store = out / "results.json"
    res: dict = {}
    if store.is_file():
        old = json.loads(store.read_text())
        if old.get("quick") == a.quick:
            res = old["sections"]
    if a.report_only:
        only = []
    tmp = None if a.work else tempfile.TemporaryDirectory(prefix="fmgs-bench-work-")
    work = a.work or Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    info = machine_info()
    order = [
        "text",
        "pose",
        "gs",
        "field",
        "scaling",
        "floor",
        "targets",
    ]  # gs first: the field reuses its fit
    t_all = time.perf_counter()
    try:
        for name in [s for s in order if s in only]:
            set_threads(a.threads)
            load0 = os.getloadavg()[0]
            print(f"[{name}]", flush=True)
            t0 = time.perf_counter()
            sec = run_section(name, sizes, work, a.threads)
            sec.update(
                machine=info,
                threads=a.threads,
                seconds=time.perf_counter() - t0,
                load=[load0, os.getloadavg()[0]],
                size="quick" if a.quick else "full",
            )
            print(f"[{name}] {sec['seconds']:.0f} s", flush=True)
            res[name] = sec
            store.write_text(json.dumps({"quick": a.quick, "sections": res}, indent=1))
    finally:
        if tmp is not None:
            tmp.cleanup()
    res = {k: res[k] for k in SECTIONS if k in res}
    if not res:
        print(f"no results in {store}", file=sys.stderr)
        return 2
    store.write_text(json.dumps({"quick": a.quick, "sections": res}, indent=1))
    write_report(res, out, report, a.quick)
    fails = exact_failures(res)
    print(f"wrote {report} and {out} in {time.perf_counter() - t_all:.0f} s")
    for f in fails:
        print(f"exact point with non-zero error: {f}", file=sys.stderr)
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main())
