"""All GPU work in one command: build gsplat's kernels, run the CUDA tests, measure, write GPU.md.

    python -m benchmarks.gpu --out DIR                  # every part, most valuable first
    python -m benchmarks.gpu --out DIR --parts tests,pose --budget 540
    python -m benchmarks.gpu --out DIR --parts gs_train,field_train --limit gs_train=200
    python -m benchmarks.gpu --report-only DIR/GPU.json  # rewrite benchmarks/results/GPU.md from it

Runs offline: gsplat (``pip install 'fmgs[cuda]'`` or a carried wheel) compiles its CUDA extension on
first use with the machine's nvcc (TORCH_EXTENSIONS_DIR keeps it; default .gpubuild/ in the repo).
Each part runs in its own subprocess (``python -m benchmarks.gpu_parts`` in the repository root) with its
own time limit and writes its figures as soon as it ends: DIR/GPU.json (raw, merged with an earlier file
given by --resume) and DIR/GPU.md are rewritten after every part, so a run cut short keeps what it
measured. Parts that would not fit in --budget seconds
are skipped and reported as not run. The parts themselves live in benchmarks/gpu_parts.py.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import RESULTS, ROOT
from benchmarks.gpu_report import write_report

# Most valuable first (the order of figures); seconds each may take at most.
PARTS: dict[str, int] = {
    "env": 60,
    "build": 540,
    "tests": 240,
    "pose": 300,
    "paper": 180,
    "agreement": 240,
    "chunks": 120,
    "gs_train": 540,
    "field_train": 420,
    "text10m": 420,
}


def part_env() -> dict[str, str]:
    """Environment for the part subprocesses: where gsplat builds, for which GPU, with how many jobs."""
    env = dict(os.environ)
    env.setdefault("TORCH_EXTENSIONS_DIR", str(ROOT / ".gpubuild" / "torch_extensions"))
    env.setdefault("MAX_JOBS", str(os.cpu_count() or 4))
    env.setdefault("PYTHONUNBUFFERED", "1")
    # Processes the parts start (pytest, servers) import this checkout even where it is not installed.
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    if "TORCH_CUDA_ARCH_LIST" not in env:
        try:
            import torch

            if torch.cuda.is_available():
                major, minor = torch.cuda.get_device_capability(0)
                env["TORCH_CUDA_ARCH_LIST"] = f"{major}.{minor}"
        except ImportError:
            pass
    return env


def run_part(name: str, work: Path, limit: float, quick: bool, log) -> dict:
    """Run one part in a subprocess; its JSON figures, or a record of how it failed."""
    res_file = work / f"part-{name}.json"
    res_file.unlink(missing_ok=True)
    cmd = [sys.executable, "-X", "faulthandler", "-m", "benchmarks.gpu_parts", name]
    cmd += ["--work", str(work)]
    if quick:
        cmd.append("--quick")
    t0 = time.perf_counter()
    try:
        env = part_env()
        env["FMGS_PART_LIMIT_S"] = str(limit)
        p = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=limit, check=False)
        rc, text = p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as e:
        rc = "timeout"
        text = (e.stdout or b"").decode(errors="replace") + (e.stderr or b"").decode(errors="replace")
    secs = time.perf_counter() - t0
    log.write(f"\n===== {name}: rc={rc} {secs:.1f}s =====\n{text[:4000]}\n...\n{text[-16000:]}\n")
    log.flush()
    res = json.loads(res_file.read_text()) if res_file.is_file() else {}
    res["_part"] = {"rc": rc, "seconds": round(secs, 1), "limit_s": limit}
    if rc != 0 and "error" not in res:
        res["error"] = (text.strip().splitlines() or ["no output"])[-1][:500]
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=RESULTS, help="GPU.md, GPU.json, gpu-log.txt")
    ap.add_argument("--work", type=Path, default=Path("/tmp/fmgs-gpu"), help="scratch (packages, fits)")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma list from {list(PARTS)}")
    ap.add_argument("--budget", type=float, default=1800.0, help="seconds for the whole run")
    ap.add_argument(
        "--limit",
        action="append",
        default=[],
        metavar="PART=S",
        help="cap a part's seconds below its default (repeatable): gs_train=200 leaves time for later parts",
    )
    ap.add_argument("--resume", type=Path, help="an earlier GPU.json whose parts are kept unless rerun")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (checks the script, not the GPU)")
    ap.add_argument("--report-only", type=Path, help="rewrite benchmarks/results/GPU.md from this GPU.json")
    args = ap.parse_args()
    if args.report_only:
        write_report(json.loads(args.report_only.read_text()), RESULTS / "GPU.md")
        return 0
    parts = [p for p in args.parts.split(",") if p]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        ap.error(f"unknown parts {unknown}; choose from {list(PARTS)}")
    limits = dict(PARTS)
    for item in args.limit:
        name, _, secs = item.partition("=")
        if name not in PARTS or not secs.replace(".", "", 1).isdigit():
            ap.error(f"--limit {item!r}: expected PART=SECONDS with PART in {list(PARTS)}")
        limits[name] = min(PARTS[name], float(secs))
    args.out.mkdir(parents=True, exist_ok=True)
    args.work.mkdir(parents=True, exist_ok=True)
    results: dict = json.loads(args.resume.read_text()) if args.resume else {}
    results.setdefault("parts", {})
    results["commit"] = os.environ.get("FMGS_COMMIT", results.get("commit", "unknown"))
    deadline = time.perf_counter() + args.budget
    failed = False
    this_env: dict = {}  # this run's machine (run the env part to have it named in the Parts table)
    with open(args.out / "gpu-log.txt", "a") as log:
        for name in parts:
            left = deadline - time.perf_counter()
            if left < 30:
                results["parts"][name] = {"skipped": f"no time left in the {args.budget:.0f} s budget"}
                continue
            print(f"[gpu] {name} (up to {min(limits[name], left):.0f} s)", flush=True)
            res = run_part(name, args.work, min(limits[name], left), args.quick, log)
            if name == "env":
                this_env = res
            res["_run"] = run_label(this_env, results["commit"])
            results["parts"][name] = res
            failed |= res["_part"]["rc"] != 0
            print(f"[gpu] {name}: {json.dumps(_brief(res))}", flush=True)
            (args.out / "GPU.json").write_text(json.dumps(results, indent=1, default=str))
            try:  # the raw figures are safe in GPU.json whatever the report writer makes of them
                write_report(results, args.out / "GPU.md")
            except Exception as e:
                print(f"[gpu] GPU.md not written: {type(e).__name__}: {e}", flush=True)
    return 1 if failed else 0


def run_label(env: dict, commit: str) -> str:
    """Which machine, commit and date a part's figures come from (parts of several runs share GPU.json)."""
    return f"{env.get('gpu', '?')}, {commit}, {env.get('date', '?')}"


def _brief(res: dict) -> dict:
    """The scalar figures of a part (for the console)."""
    return {k: v for k, v in res.items() if isinstance(v, int | float | str | bool) and len(str(v)) < 80}


if __name__ == "__main__":
    sys.exit(main())
