"""A robot's recording built into a scene, scored like FIELD.md, beside the same frames given true poses.

A generated cluttered scene (fmgs.synthbag) is recorded as a ROS 2 bag: a base driving once around it,
images at 15 Hz (PNG CompressedImage), tf at 50 Hz with a 0.5 s dropout, a registered depth camera, every
13th image blurred. ``fmgs build BAG`` reads it (keyframes by motion and sharpness, poses from tf, points
from depth) and builds with label targets. The same kept frames are then built again as a
``transforms.json`` dataset with the generator's own poses and surface points (the path every other
report measures). Both packages are scored through the engine the server runs, on the recording's
held-out keyframes, in the map frame: what the recording path costs, if anything.

    python -m benchmarks.bag --out /tmp/bag --report
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import machine, machine_words
from benchmarks.unseen import present_absent, scene_quality

ROOT = Path(__file__).resolve().parents[1]
REPORT = ROOT / "benchmarks" / "results" / "BAG.md"


def _build(source: Path, name: str, out: Path, rec: Path, args) -> None:
    from fmgs.cli import main as fmgs

    cmd = ["build", str(source), "--name", name, "--models", str(out / "models"), "--targets", "labels"]
    cmd += ["--labels", str(rec / "labels"), "--names", str(rec / "scene.json")]
    cmd += ["--gs-steps", str(args.gs_steps), "--grad-threshold", str(args.grad_threshold)]
    cmd += ["--field-steps", str(args.field_steps)]
    if args.threads:  # auto counts idle cores from the load average, which lags a process that just ended
        cmd += ["--gs-threads", str(args.threads), "--field-threads", str(args.threads)]
    assert fmgs(cmd) == 0


FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV camera axes to OpenGL's (transforms.json's), and back."""


def _true_poses(rec: Path) -> dict[int, np.ndarray]:
    """Image stamp -> the generator's map_T_optical (OpenCV axes), from truth.json."""
    truth = json.loads((rec / "truth.json").read_text())
    return {s: np.array(T) for s, T in zip(truth["image_stamps"], truth["map_T_optical"], strict=True)}


def _truth_dataset(recording: Path, rec: Path, out: Path) -> Path:
    """The recording's kept frames with the generator's poses and surface points (transforms.json)."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(recording, out)
    poses = _true_poses(rec)
    meta = json.loads((out / "transforms.json").read_text())
    for f in meta["frames"]:
        f["transform_matrix"] = (poses[f["stamp_ns"]] @ FLIP).tolist()
    shutil.copy(rec / "render" / "points3D.ply", out / "points3D.ply")
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out


def _pose_error(recording: Path, rec: Path) -> dict:
    from fmgs.data.tf import matrix_to_quat

    poses = _true_poses(rec)
    meta = json.loads((recording / "transforms.json").read_text())
    t_err, r_err = [], []
    for f in meta["frames"]:
        got, want = np.array(f["transform_matrix"]) @ FLIP, poses[f["stamp_ns"]]
        t_err.append(float(np.linalg.norm(got[:3, 3] - want[:3, 3])))
        q = matrix_to_quat(want[:3, :3].T @ got[:3, :3])  # the angle from its quaternion: no arccos floor
        r_err.append(float(np.degrees(2 * np.arctan2(np.linalg.norm(q[:3]), abs(q[3])))))
    return {"max_translation_m": max(t_err), "max_rotation_deg": max(r_err)}


def _score(package: Path, data: Path) -> dict:
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine

    engine = SceneEngine.open(package)
    ds = load_dataset(data)
    _, test = ds.split(HOLDOUT_EVERY)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    q = scene_quality(engine, ds, MiniLMTextEncoder(), test, data, names)
    q.update(views_test=len(test), embedded=engine.num_embedded, gaussians=engine.num_gaussians)
    return q


def run(args) -> dict:
    from fmgs.synth import SynthConfig
    from fmgs.synthbag import RobotPathConfig, write_robot_bag

    out = Path(args.out)
    rec = out / "rec"
    w, h = (int(v) for v in args.size.split("x"))
    scene = SynthConfig(views=0, width=w, height=h, objects=10, seed=args.seed, preset="cluttered")
    path = RobotPathConfig(
        synth=scene,
        seconds=args.seconds,
        dropout=(args.seconds / 4, 0.5),
        blur_every=13,
        transport="compressed",
    )
    if not (rec / "truth.json").is_file():
        t0 = time.perf_counter()
        write_robot_bag(rec, path)
        print(f"recording written in {time.perf_counter() - t0:.0f} s", flush=True)
    models = out / "models"

    def built(source: Path, name: str) -> dict:
        """Build (or, with --reuse, take the package already in OUT); the times are the 3DGS and field
        stages' own records (gs/train.json, field/field_train.json), which a resumed build keeps."""
        if not (args.reuse and (models / name / "manifest.json").is_file()):
            _build(source, name, out, rec, args)
        work = models / ".work" / name
        geometry = json.loads((work / "geometry.json").read_text())
        gs = json.loads((work / "gs" / "train.json").read_text())
        field = json.loads((work / "field" / "field_train.json").read_text())
        return {
            "gs_seconds": gs["seconds"], "gs_threads": gs["threads"], "field_seconds": field["seconds"],
            "field_threads": field["threads"], "psnr": geometry["psnr"], "geometry": geometry,
        }  # fmt: skip

    rows = {"bag": built(rec / "bag", "bag")}
    recording = models / ".work" / "bag" / "recording"
    # Labels and scene.json beside the kept frames, to score them (the import does not carry labels).
    shutil.copytree(rec / "labels", recording / "labels", dirs_exist_ok=True)
    shutil.copy(rec / "scene.json", recording / "scene.json")
    if not args.skip_truth:
        rows["truth"] = built(_truth_dataset(recording, rec, out / "truth-poses"), "truth")
    res = {
        "seed": args.seed,
        "size": args.size,
        "seconds": args.seconds,
        "recording": rows["bag"]["geometry"]["recording"],
        "pose_error": _pose_error(recording, rec),
    }
    for name, row in rows.items():
        row.pop("geometry")
        res[name] = {**row, **_score(models / name, recording)}
    return res


def _pct(v: float) -> str:
    return f"{100 * v:.1f}%"


def report(res: dict, info: dict) -> str:
    rc = res["recording"]
    dropped = ", ".join(f"{k} {v}" for k, v in sorted(rc["dropped"].items()))
    pe = res["pose_error"]
    head = "| poses | 3DGS s (threads) | field s (threads) | held-out PSNR | Gaussians (embedded) | 2D loc. "
    head += "| 3D loc. | mIoU | present found "
    lines = [
        "# A robot's recording built into a scene",
        "",
        f"Measured {info['when']} on {info['machine']}, commit {info['commit']}. "
        f"Reproduce: `{info['command']}`.",
        "",
        f"Scene: `fmgs.synthbag` over a cluttered generated scene (seed {res['seed']}, 10 objects, "
        f"{res['size']} images): a base drives once around it in {res['seconds']:.0f} s, tf `map -> odom -> "
        "base_link -> camera_link -> camera_optical_frame` at 50 Hz with a 0.5 s dropout of `odom -> "
        "base_link`, PNG CompressedImage at 15 Hz with every 13th frame blurred (9-pixel box), a registered "
        "32FC1 depth camera. "
        + (
            "Both rows are built with the same settings (label targets; step counts in the command) on the "
            "same kept frames and scored on the same held-out frames (every 8th kept frame) in the map "
            "frame; *recording*: `fmgs build BAG` (poses from tf, points from depth); *true poses*: the kept "
            "frames as a `transforms.json` dataset with the generator's poses and surface points."
            if "truth" in res
            else "`fmgs build BAG` (poses from tf, points from depth; label targets, step counts in the "
            "command), scored on its held-out frames (every 8th kept frame) in the map frame against the "
            "generator's objects, through the engine the server runs."
        ),
        "",
        f"Frames: read {rc['read']}, kept {rc['kept']} (dropped: {dropped}); {rc['depth_points']:,} points "
        f"from depth. Poses from tf against the generator's: at most {pe['max_translation_m']:.1e} m and "
        f"{pe['max_rotation_deg']:.1e} degrees.",
        "",
        head + "| absent rejected |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, label in (("bag", "recording (tf, depth)"), ("truth", "true poses, generator points")):
        if key not in res:
            continue
        r = res[key]
        p, a = present_absent(r["presence"])
        lines.append(
            f"| {label} | {r['gs_seconds']:.0f} ({r['gs_threads']}) | {r['field_seconds']:.0f} "
            f"({r['field_threads']}) | {r['psnr']:.2f} dB | {r['gaussians']:,} "
            f"({r['embedded']:,}) | {_pct(r['localisation_2d'])} | {_pct(r['localisation_3d'])} | "
            f"{r['miou']:.3f} | {p} | {a} |"
        )
    lines += [
        "",
        "Seconds: the 3DGS and field stages' own records on this 2-core machine "
        f"({info['load']}), with the threads each stage ran on.",
        "",
    ]
    if info.get("reused"):
        lines += [
            "Scored (again) from the packages this command had built: `--reuse` builds nothing.",
            "",
        ]
    if "truth" not in res:
        lines += ["The true-pose row was not run (`--skip-truth`).", ""]
    return "\n".join(lines)


def _without_load(argv: list[str]) -> list[str]:
    """The command line less --reuse and --load TEXT (what the report records as its command)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--load":
            skip = True
        elif a != "--reuse" and not a.startswith("--load="):
            out.append(a)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=107)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--size", default="96x72")
    ap.add_argument("--gs-steps", type=int, default=3000)
    ap.add_argument("--grad-threshold", type=float, default=0.001)
    ap.add_argument("--field-steps", type=int, default=1500)
    ap.add_argument("--threads", type=int, default=0, help="threads of the 3DGS and field stages (0: auto)")
    ap.add_argument("--skip-truth", action="store_true", help="build and score the recording only")
    ap.add_argument(
        "--reuse",
        action="store_true",
        help="score the packages already built in OUT instead of building them",
    )
    ap.add_argument("--quick", action="store_true", help="CI size: a 10 s drive at 64x48, short stages")
    ap.add_argument("--report", action="store_true", help="also write benchmarks/results/BAG.md")
    ap.add_argument("--load", default="idle", help="what else ran on the machine (for the report)")
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.size, args.gs_steps, args.field_steps = 10.0, "64x48", 200, 100
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = run(args)
    m = machine()
    info = {
        "when": m["date"],
        "machine": machine_words(m).rsplit(", commit", 1)[0],
        "commit": m["commit"],
        # --reuse only skips builds an earlier run of the same command made: the command reproduces them
        "command": "python -m benchmarks.bag " + " ".join(_without_load(sys.argv[1:])),
        "load": args.load,
        "reused": args.reuse,
    }
    (out / "bag.json").write_text(json.dumps({"result": res, "info": info}, indent=1, default=str))
    print(report(res, info))
    if args.report and not args.quick:
        REPORT.write_text(report(res, info))
        (REPORT.with_suffix(".json")).write_text(
            json.dumps({"result": res, "info": info}, indent=1, default=str)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
