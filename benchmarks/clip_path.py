"""The CLIP-target path on meaning: scenes of the wider generated world built with ``--targets clip`` through
the full hybrid pyramid, with the CLIP stand-in (fmgs.features.standin) and the DINO stand-in
(fmgs.features.standin_dino), side by side with label targets on the same scenes and the same geometry.

    python -m benchmarks.clip_path --out OUT [--seeds 201,202,203] [--variants ...] [--report]
    python -m benchmarks.clip_path --out OUT --quick      # a smoke run: one 64x48 scene, short stages

Per unseen seed (no setting and no stand-in training used it; odd seeds open, even ones in a room):
``fmgs synth --preset world --objects 10 --novel 3`` (three objects with colour-shape pairs no stand-in
saw), ``fmgs build --targets labels`` at the defaults (benchmarks.unseen.build_scene), then one
``fmgs build --targets clip --clip-model standin:... --dino-model standin-dino:... --ply`` per variant
(VARIANTS: the paper's equal mean of the scales, the DINO-weighted blends, the default without the
dot-product similarity loss and without DINO) on that build's 3DGS, each scored on the held-out views as
served (2D and 3D localisation, mIoU, presence), the three novel objects also on their own. Then the
target maps alone, before distillation, per candidate (benchmarks.clip_targets). Writes clip_path.json
and CLIP_PATH.md (with --report, both into benchmarks/results/ as CLIP_PATH.json and CLIP_PATH.md). Builds
already in OUT are kept, and so are a package's scores (OUT/score-NAME.json) while its manifest is the
same: delete them to score again after changing how packages are scored.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.clip_variants import (
    DESCRIBE,
    ROOT,
    STANDIN,
    STANDIN_DINO,
    STANDIN_SEG,
    VARIANTS,
    build_record,
    clip_build,
    variant_name,
)
from benchmarks.common import command_line, machine, machine_words, save_report
from benchmarks.unseen import PRESENT_KINDS, build_scene, presence_rates, scene_quality, score_presence
from fmgs.query.instances import InstanceConfig
from fmgs.query.presence import PresenceConfig

NOVEL = 3
"""Objects per scene with a held-out colour-shape pair."""


def synth_flags(seed: int) -> tuple[str, ...]:
    return ("--novel", str(NOVEL), "--backdrop", "constant" if seed % 2 else "walls")


QUORUM = InstanceConfig().min_points
"""The presence quorum measured beside the served one: an instance's worth of Gaussians."""
APART = {
    "presence_best": PresenceConfig(rule="each"),
    "presence_quorum": PresenceConfig(rule="each", quorum=QUORUM),
    "presence_mean": PresenceConfig(rule="mean"),
}
"""Presence rules scored beside the served one, each under its own key (added to kept scores that lack it,
so that older scores are kept)."""


def scene_targets(out: Path, data: Path, standin: Path, dino: Path, views: int, oracle: bool = False) -> dict:
    """benchmarks.clip_targets.target_candidates of one scene, kept in OUT/targets-SCENE.json for the same
    views, stand-ins and oracle flag."""
    from benchmarks.clip_targets import CANDIDATE_SET, target_candidates

    key = {"views": views, "oracle": oracle, "standin": str(standin), "standin_dino": str(dino),
           "candidates": CANDIDATE_SET}  # fmt: skip
    kept = out / f"targets-{data.name}.json"
    stored = json.loads(kept.read_text()) if kept.is_file() else {}
    if stored.get("key") != key:
        stored = {"key": key, "candidates": target_candidates(data, standin, dino, views, oracle=oracle)}
        kept.write_text(json.dumps(stored))
    return stored["candidates"]


def package_bytes(package: Path) -> dict:
    """Bytes of the language part per embedded Gaussian (stored embeddings and the compact query state),
    and of the whole package per Gaussian."""
    from fmgs.scene.manifest import Manifest

    m = Manifest.read(package)
    size = {p.name: p.stat().st_size for p in package.iterdir() if p.is_file()}
    lang = size.get("embeddings.safetensors", 0) + size.get("query_state.safetensors", 0)
    return {
        "language_per_embedded": lang / max(m.num_selected, 1),
        "package_per_gaussian": sum(size.values()) / max(m.num_gaussians, 1),
        "package": sum(size.values()),
    }


def novel_scores(q: dict, data: Path) -> dict:
    """The held-out-name objects' own 2D hits and queries, 3D hits, IoU and presence (found / asked)."""
    meta = json.loads((data / "scene.json").read_text())
    novel = [o["name"] for o in meta["objects"] if o.get("novel")]
    h2 = sum(q["per_object_2d"].get(n, [0, 0])[0] for n in novel)
    n2 = sum(q["per_object_2d"].get(n, [0, 0])[1] for n in novel)
    found = [r for r in q["presence"] if r["kind"] == "name" and r["text"] in novel]
    return {
        "names": novel,
        "hits_2d": h2,
        "queries_2d": n2,
        "hits_3d": sum(bool(q["per_object_3d"].get(n)) for n in novel),
        "objects": len(novel),
        "iou": [q["class_iou"][n] for n in novel if n in q["class_iou"]],
        "found": sum(r["found"] for r in found),
    }


def score(out: Path, seed: int, data: Path, variants: list[str]) -> dict:
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine

    ds = load_dataset(data)
    enc = MiniLMTextEncoder()
    _, test = ds.split(HOLDOUT_EVERY)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    row: dict = {"seed": seed, "views_test": len(test), "objects": names[2:], "kinds": {}}
    for kind in ["labels", *variants]:
        name = variant_name(seed, kind)
        pkg = out / "models" / name
        if not (pkg / "manifest.json").is_file():  # --no-build: a variant not built for this seed
            continue
        key = hashlib.sha256((pkg / "manifest.json").read_bytes()).hexdigest()
        kept = out / f"score-{name}.json"  # the package's scores, kept while its manifest is the same
        stored = json.loads(kept.read_text()) if kept.is_file() else {}
        engine = None  # opened only when something is to be scored
        if stored.get("manifest_sha256") == key:
            q = stored["quality"]
        else:
            engine = SceneEngine.open(pkg)
            q = scene_quality(engine, ds, enc, test, data, names)
            q["novel"] = novel_scores(q, data)
            q["embedded"] = engine.num_embedded
            q["bytes"] = package_bytes(pkg)
            kept.write_text(json.dumps({"manifest_sha256": key, "quality": q}, default=float))
        for rule, cfg in APART.items():
            if rule not in q:
                engine = engine or SceneEngine.open(pkg)
                q[rule] = score_presence(engine, enc, names, cfg)
                kept.write_text(json.dumps({"manifest_sha256": key, "quality": q}, default=float))
        q["build_seconds"] = json.loads(build_record(out, seed, kind).read_text())["seconds"]
        row["kinds"][kind] = q
    return row


def presence_accuracy(q: dict, key: str = "") -> tuple[int, int, int, int]:
    """(present found, present, absent not found, absent) of the presence rows q[key]; by default those of
    the single best Gaussian's rule (the served one until the mean replaced it; ``q["presence"]``, as
    served, in scores made before)."""
    key = key or ("presence_best" if "presence_best" in q else "presence")
    sums = [[0, 0], [0, 0]]
    for kind, (ok, n) in presence_rates(q[key]).items():
        s = sums[0 if kind in PRESENT_KINDS else 1]
        s[0] += ok
        s[1] += n
    return sums[0][0], sums[0][1], sums[1][0], sums[1][1]


def rule_rates(qs: list[dict], key: str) -> dict:
    """Presence, present found and absent rejected of the rows q[key] pooled over the scores ``qs``; None
    where some score lacks them (a rule added after its build was gone)."""
    if key == "presence_best":  # scores made while it was served have it as "presence"
        qs = [q if key in q else {**q, key: q["presence"]} for q in qs]
    if not qs or any(key not in q for q in qs):
        return dict.fromkeys(("presence", "present_found", "absent_rejected"))
    f, p, a, n = (sum(x) for x in zip(*(presence_accuracy(q, key) for q in qs), strict=True))
    return {
        "presence": (f + a) / max(p + n, 1),
        "present_found": f / max(p, 1),
        "absent_rejected": a / max(n, 1),
    }


def summary(rows: list[dict], kind: str) -> dict:
    """Means over the scenes of one kind's scores, presence pooled, novel objects pooled."""
    qs = [r["kinds"][kind] for r in rows if kind in r["kinds"]]
    pf, pn, af, an = (sum(x) for x in zip(*(presence_accuracy(q) for q in qs), strict=True))
    nov = [q["novel"] for q in qs]
    ious = [i for n in nov for i in n["iou"]]
    return {
        "scenes": len(qs),
        "localisation_2d": float(np.mean([q["localisation_2d"] for q in qs])),
        "localisation_3d": float(np.mean([q["localisation_3d"] for q in qs])),
        "miou": float(np.mean([q["miou"] for q in qs])),
        "present_found": pf / max(pn, 1),
        "absent_rejected": af / max(an, 1),
        "presence": (pf + af) / max(pn + an, 1),
        **{f"{rule.split('_')[1]}_{k}": v for rule in APART for k, v in rule_rates(qs, rule).items()},
        "build_seconds": float(np.mean([q["build_seconds"] for q in qs])),
        "language_bytes": float(np.mean([q["bytes"]["language_per_embedded"] for q in qs])),
        "package_bytes": float(np.mean([q["bytes"]["package_per_gaussian"] for q in qs])),
        "novel_2d": sum(n["hits_2d"] for n in nov) / max(sum(n["queries_2d"] for n in nov), 1),
        "novel_3d": sum(n["hits_3d"] for n in nov) / max(sum(n["objects"] for n in nov), 1),
        "novel_iou": float(np.mean(ious)) if ious else float("nan"),
        "novel_found": sum(n["found"] for n in nov) / max(sum(n["objects"] for n in nov), 1),
    }


def standin_errors(cfg: dict) -> str:
    """The CLIP stand-in's held-out object crops per scale and how it errs, where its config has them."""
    per_scale = cfg.get("heldout_object_crop_accuracy_per_scale")
    if not per_scale:
        return ""
    scales = sorted(per_scale, key=float)
    return (
        " Crops whose most salient label is an object are named right "
        f"{per_scale[scales[0]]:.3f} of the time at the finest scale ({scales[0]}) and "
        f"{per_scale[scales[-1]]:.3f} at the coarsest ({scales[-1]}); "
        f"{cfg['heldout_object_errors_named_as_stuff']:.0%} of the misnamed ones are named as floor or wall, "
        "not as another object."
    )


REFIT = "the label path on the added variants' builds"
"""Section of the report on the label builds an addition (``--add-to``) was made on."""


def refit_section(rows: list[dict]) -> list[str]:
    """The label path (and any variant built again) on the label builds the added variants were distilled
    on, beside the builds in the tables (the 3DGS is fitted again, so figures may differ); empty when
    nothing was added."""
    if not any("refit_labels" in r for r in rows):
        return []
    lines = [
        "",
        f"## {REFIT[0].upper()}{REFIT[1:]}",
        "",
        "Variants added to this report later were distilled on label builds made again from the same "
        "scenes with the same settings (the 3DGS fitted again), compare them with these label figures; "
        "a variant already in the tables and built again on them is shown both ways too:",
        "",
        "| seed | targets | build | 2D loc. | 3D loc. | mIoU | present found | absent rejected |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in (r for r in rows if "refit_labels" in r):
        again = {"labels": r["refit_labels"], **r.get("refit_variants", {})}
        for kind, new in again.items():
            for which, q in (("in the tables", r["kinds"].get(kind)), ("made again", new)):
                if q is None:  # a variant the first run did not build for this seed
                    continue
                pf, pn, af, an = presence_accuracy(q)
                lines.append(
                    f"| {r['seed']} | {kind} | {which} | {q['localisation_2d']:.3f} | "
                    f"{q['localisation_3d']:.3f} | {q['miou']:.3f} | {pf}/{pn} | {af}/{an} |"
                )
    return lines


def build_scores(q: dict) -> dict:
    """A build's scores without the presence rules scored apart (``APART``): what tells builds apart."""
    return {k: v for k, v in q.items() if k not in APART}


def add_to(stored: dict, rows: list[dict], variants: list[str], addition: dict) -> dict:
    """``stored`` (a clip_path.json) with ``variants`` of ``rows`` (scored on label builds made again)
    added to its rows of the same seeds, those label figures as ``refit_labels``, and ``addition``
    (command, machine) listed. A variant the stored rows already hold keeps them: its new figures go to
    ``refit_variants``, shown beside them. Every addition must be made on the same label builds (the
    refit section compares with one). A build the report holds already (the same scores but for the rules
    scored apart) is scored again in place: its ``APART`` rules are added (``addition["rescored"]``)."""
    by_seed = {r["seed"]: r for r in rows}
    missing = [r["seed"] for r in stored["rows"] if r["seed"] not in by_seed]
    if missing:
        raise ValueError(f"no new scores for seeds {missing} of the stored report")
    rescored = set()
    for r in stored["rows"]:
        new = by_seed[r["seed"]]
        if build_scores(r.get("refit_labels", new["kinds"]["labels"])) != build_scores(
            new["kinds"]["labels"]
        ):
            raise ValueError(
                f"seed {r['seed']}: the label build differs from the one earlier additions were made on"
            )
        r["refit_labels"] = new["kinds"]["labels"]
        for v in (v for v in variants if v in new["kinds"]):
            q, again = new["kinds"][v], r.setdefault("refit_variants", {})
            held = [d for d in (r["kinds"], again) if v in d and build_scores(d[v]) == build_scores(q)]
            if held:
                held[0][v] = q
                rescored.add(v)
            elif v in r["kinds"]:
                again[v] = q
            else:
                r["kinds"][v] = q
            if not again:
                del r["refit_variants"]
    stored["variants"] = [*stored["variants"], *(v for v in variants if v not in stored["variants"])]
    stored["additions"] = [*stored.get("additions", []), {**addition, "rescored": sorted(rescored)}]
    return stored


def mean_section(rows: list[dict], kinds: list[str]) -> list[str]:
    """Presence by the three rules (``APART``) on every build scored with the mean, the tables' and those
    made again; empty when none was."""
    builds = [(k, "in the tables", [r["kinds"][k] for r in rows if k in r["kinds"]]) for k in kinds]
    again = {"labels": [r["refit_labels"] for r in rows if "refit_labels" in r]}
    for r in rows:
        for k, q in r.get("refit_variants", {}).items():
            again.setdefault(k, []).append(q)
    builds += [(k, "made again", qs) for k, qs in again.items()]
    have = [(k, w, qs) for k, w, qs in builds if qs and all("presence_mean" in q for q in qs)]
    if not have:
        return []
    cfg = PresenceConfig()
    lines = [
        "",
        "## Presence by the best Gaussians' mean (the served rule)",
        "",
        f'The served rule (`PresenceConfig.rule` "{cfg.rule}") takes the query\'s {cfg.pool} best '
        f"Gaussians (`PresenceConfig.pool`, an instance's worth) as one group: their mean embedding must be "
        "closer to the query than to every negative the query does not mean, as mask-based methods "
        "classify a segment by its mean feature. The tables above were measured with the rule before it "
        f'("each", quorum 1: the single best of the {cfg.rows} best Gaussians decides). It was chosen on '
        "a scene no table here scores (seed 301, see docs/presence.md). On every build scored with the "
        "mean, the same queries, pooled over the build's scenes:",
        "",
        f"| targets | build | scenes | best Gaussian | quorum of {QUORUM} | mean | present found | "
        "absent rejected |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for k, which, qs in have:
        one, q, m = (rule_rates(qs, key) for key in APART)
        lines.append(
            f"| {k} | {which} | {len(qs)} | {one['presence']:.3f} | {q['presence']:.3f} | "
            f"{m['presence']:.3f} | {m['present_found']:.3f} | {m['absent_rejected']:.3f} |"
        )
    return lines


def addition_words(a: dict) -> str:
    """The report's sentence on one ``--add-to`` run: variants built, or builds the report holds scored
    again (their presence rules)."""
    when = f"{a['machine']['date']} on {machine_words(a['machine'])}"
    built = [v for v in a["variants"] if v not in a.get("rescored", ())]
    out = ""
    if built:
        out += (
            f" Added {when}: {', '.join(built)}, one run of `{a['command']}`, on label builds made again "
            f"for it (see {REFIT})."
        )
    if a.get("rescored"):
        out += (
            f" Scored again {when}, the presence rules of the builds the report holds for "
            f"{', '.join(a['rescored'])} (and their label builds), one run of `{a['command']}`."
        )
    return out


def segmenter_config(variants: list[str]) -> dict:
    """{"standin_seg": the segmenter stand-in's config} when a variant uses it, else {}."""
    if not any(VARIANTS[v].get("segments") for v in variants):
        return {}
    return {"standin_seg": json.loads((STANDIN_SEG / "standin_seg.json").read_text())}


def segmenter_words(cfg: dict | None) -> str:
    """The report's sentence on the segmenter stand-in (none without a segments variant)."""
    if not cfg:
        return ""
    h = cfg["heldout"]
    return (
        f" The segmenter stand-in (a small U-Net, `{cfg['command']}`, SAM's role) is trained on the instance "
        f"masks of {len(cfg['train_seeds'])} other world scenes (which neighbouring pixels lie on one "
        "surface), never on names; its segments are the connected components of the pairs it joins with "
        f"affinity above {cfg['join']}. On held-out scenes {h['objects_iou_over_half']:.0%} of objects have "
        f"a segment overlapping their mask by more than half (mean best IoU {h['object_best_iou']:.2f}) and "
        f"{h['object_pixels_in_own_segment']:.0%} of object pixels lie in a segment mostly their own."
    )


def report(d: dict) -> str:
    rows, info, cmd = d["rows"], d["machine"], d["command"]
    kinds = ["labels", *d["variants"]]
    s = {k: summary(rows, k) for k in kinds}
    clip_cfg, dino_cfg = d["standin"], d["standin_dino"]
    lines = [
        "# The CLIP-target path on meaning, in the wider world",
        "",
        f"Measured {info['date']} on {machine_words(info)}, one run of `{cmd}`."
        + "".join(map(addition_words, d.get("additions", []))),
        "",
        f"Scenes: `fmgs synth --preset world --objects 10 --novel {NOVEL}` (fmgs.synthworld: objects of "
        'distinct shapes from 15, each in one of 12 colours and one of 11 surface textures, named "<colour> '
        '<texture> <shape>", sizes from small to large; odd seeds open, even seeds in a room of textured '
        f"walls), {NOVEL} objects per scene with a colour-shape pair held out of every stand-in's training. "
        "No setting and no stand-in training used these seeds. Each scene is built with label targets "
        "(`--targets labels`: the names' MiniLM embeddings painted by the label masks) and with CLIP "
        "targets once per variant below, all on the label build's 3DGS: the full hybrid crop pyramid at "
        "its defaults, every crop embedded by the CLIP stand-in, blended across scales as the variant "
        "says, the DINO stand-in's dense map as the DINO target. Every scene is queried with MiniLM and "
        "scored on the held-out views as served.",
        "",
        f"The CLIP stand-in (a small CNN, {'two convs' if clip_cfg.get('blocks', 1) == 2 else 'one conv'} "
        f"per stage, `{clip_cfg['command']}`) is trained into MiniLM's space on "
        f"crops of {len(clip_cfg['train_seeds'])} other world scenes, against what each crop shows (each "
        "name's share under a centre-weighted window, over captions of varying detail); held-out crop "
        f"accuracy {clip_cfg['heldout_crop_accuracy']:.3f}, {clip_cfg['heldout_novel_crop_accuracy']:.3f} on "
        "crops of held-out names." + standin_errors(clip_cfg) + " The DINO stand-in (a small CNN, "
        f"`{dino_cfg['command']}`) is trained without labels (dense clustering across augmented views); on "
        "held-out scenes the cosine of two pixels' features is "
        f"{dino_cfg['heldout']['trained']['within_object_cosine']:.2f} within one object and "
        f"{dino_cfg['heldout']['trained']['across_object_cosine']:.2f} across two, and a pixel's nearest "
        "neighbour in feature space has its label "
        f"{dino_cfg['heldout']['trained']['nearest_neighbour_label_agreement']:.0%} of the time (random "
        f"weights: {dino_cfg['heldout']['random_weights']['nearest_neighbour_label_agreement']:.0%}; raw "
        f"colour: {dino_cfg['heldout']['raw_colour']['nearest_neighbour_label_agreement']:.0%})."
        + segmenter_words(d.get("standin_seg")),
        "",
        "Variants: "
        + "; ".join(
            [f"**{k}**: {v}" for k, v in DESCRIBE.items() if k in kinds]
            + ["*no-dotsim*: without the dot-product similarity loss (the paper's ablation)"]
            * any("no-dotsim" in k for k in kinds)
            + ["*no-DINO*: no DINO target at all (language loss only)"] * any("no-DINO" in k for k in kinds)
        )
        + ".",
        "",
        "## Means over the scenes",
        "",
        "| targets | scenes | 2D loc. | 3D loc. | mIoU | presence | present found | absent rejected | "
        "build s | language B / embedded Gaussian | package B / Gaussian |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for k in kinds:
        v = s[k]
        lines.append(
            f"| {k} | {v['scenes']} | {v['localisation_2d']:.3f} | {v['localisation_3d']:.3f} | "
            f"{v['miou']:.3f} | "
            f"{v['presence']:.3f} | {v['present_found']:.3f} | {v['absent_rejected']:.3f} | "
            f"{v['build_seconds']:.0f} | {v['language_bytes']:.0f} | {v['package_bytes']:.0f} |"
        )
    lines += [
        "",
        "Build seconds: the label build includes the 3DGS fit (the CLIP builds reuse it); language bytes: "
        "the stored float16 embedding and the compact query state of each embedded Gaussian.",
        "",
        f"## Presence with a quorum of {QUORUM} Gaussians",
        "",
        "Presence in the tables is the single best's of the query's "
        f'{PresenceConfig().rows} best Gaussians (`PresenceConfig.rule` "each", quorum 1: the rule served '
        "when they were measured); with a quorum of "
        f"{QUORUM} (instance grouping's `min_points`), the {QUORUM} best must each be closer to the query "
        "than to every negative it does not mean. Same packages, same queries:",
        "",
        "| targets | presence (quorum 1) | presence | present found | absent rejected |",
        "|---|---:|---:|---:|---:|",
        *(
            f"| {k} | {s[k]['presence']:.3f} | {s[k]['quorum_presence']:.3f} | "
            f"{s[k]['quorum_present_found']:.3f} | {s[k]['quorum_absent_rejected']:.3f} |"
            for k in kinds
        ),
        *mean_section(rows, kinds),
        "",
        f"## Held-out names ({NOVEL} objects per scene, colour-shape pairs no stand-in saw)",
        "",
        "| targets | 2D loc. | 3D loc. | IoU | name found |",
        "|---|---:|---:|---:|---:|",
    ]
    for k in kinds:
        v = s[k]
        cells = " | ".join(f"{v[m]:.3f}" for m in ("novel_2d", "novel_3d", "novel_iou", "novel_found"))
        lines.append(f"| {k} | {cells} |")
    lines += [
        "",
        "## Per scene",
        "",
        "| seed | targets | 2D loc. | 3D loc. | mIoU | present found | absent rejected | s |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        for k in (k for k in kinds if k in r["kinds"]):
            q = r["kinds"][k]
            pf, pn, af, an = presence_accuracy(q)
            lines.append(
                f"| {r['seed']} | {k} | {q['localisation_2d']:.3f} | {q['localisation_3d']:.3f} | "
                f"{q['miou']:.3f} | {pf}/{pn} | {af}/{an} | {q['build_seconds']:.0f} |"
            )
    lines += ["", "Objects: " + "; ".join(f"seed {r['seed']}: {', '.join(r['objects'])}" for r in rows)]
    if d.get("target_maps"):
        from benchmarks.clip_targets import has_oracle_rows, table

        lines += [
            "",
            "## The targets alone, before distillation",
            "",
            f"The CLIP targets of the first {d['target_views']} views of every scene, per candidate, scored "
            "as segmentation is (argmax over the scene's names but the background, on pixels with "
            "geometry), pixels pooled over the scenes, mIoU averaged: each scale alone, the blends, each "
            "blend pooled within DINO-coherent neighbourhoods (`pool_regions`), LERF's query-time scale "
            "selection (each name scored by its best scale: what a field with a map per scale answers), and "
            "region crops (benchmarks.region_crops, the mask-based methods' way: one tight crop per region "
            "grown over the DINO map, or per label mask as the bound better masks could reach, averaged with "
            "the finest scale's map; *masked*: each crop black outside its region, as LangSplat crops its "
            "SAM masks)."
            + (
                " *No naming error*: each blend with every crop embedded as the stand-in is trained to embed "
                "it, from the label map (benchmarks.clip_oracle)."
                if has_oracle_rows(d["target_maps"])
                else ""
            ),
            "",
            *table(d["target_maps"]),
        ]
    lines += refit_section(rows)
    if d.get("notes"):
        lines += ["", "## Notes on this run", "", *(f"- {n}" for n in d["notes"])]
    lines += [
        "",
        "## What the stand-ins can and cannot show",
        "",
        "The stand-ins give the CLIP path meaning: a crop's embedding lands near the names of what it shows, "
        "and DINO's features group what looks alike, so a misplaced crop, a wrong blend of scales, a shifted "
        "interpolation or a regulariser that blurs boundaries would cost localisation and IoU here. They "
        "cannot show how CLIP's own embeddings of real photos behave: its open vocabulary beyond a world of "
        "15 shapes, 12 colours and 11 textures, its narrow similarity range (best cosines 0.2-0.35), its "
        "response to context; nor DINO's own semantics (parts of one object that look different grouped "
        "together). Those need pretrained weights.",
        "",
    ]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seeds", default="201,202,203")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="CLIP variants to build (VARIANTS)")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--size", default="128x96")
    ap.add_argument("--gs-steps", type=int, default=3000)
    ap.add_argument("--field-steps", type=int, default=1500, help="field steps of every build (default 1500)")
    ap.add_argument(
        "--grad-threshold", type=float, default=0.001, help="3DGS densification threshold (default 0.001)"
    )
    ap.add_argument("--field-threads", type=int, default=0, help="CLIP builds' field threads (0: auto)")
    ap.add_argument(
        "--target-views",
        type=int,
        default=6,
        help="views per scene of the target-map table (0: no table, e.g. for scenes another report's "
        "table holds: it depends on the scenes, not the builds)",
    )
    ap.add_argument("--standin", default=str(STANDIN), help="the CLIP stand-in's folder")
    ap.add_argument("--standin-dino", default=str(STANDIN_DINO), help="the DINO stand-in's folder")
    ap.add_argument("--quick", action="store_true", help="smoke run: one 64x48 scene, short stages")
    ap.add_argument("--from-json", metavar="JSON", help="only write the report again from a clip_path.json")
    ap.add_argument("--report", action="store_true", help="also write the report into benchmarks/results/")
    ap.add_argument(
        "--report-name",
        default="CLIP_PATH",
        help="the report's name: NAME.md and NAME.json (default CLIP_PATH; another name for a comparison "
        "made on other label builds than the stored report's)",
    )
    ap.add_argument("--note", action="append", default=[], help="a line for the report's notes (repeatable)")
    ap.add_argument(
        "--add-to",
        metavar="JSON",
        help="add the variants scored here (on label builds made again in OUT) to a stored clip_path.json "
        "and write the report from it; its target-map table and notes are kept (with --note: appended)",
    )
    ap.add_argument(
        "--no-build",
        action="store_true",
        help="build nothing: score the builds already in OUT (a variant "
        "missing for a seed is left out of that seed's rows; the tables say over how many scenes)",
    )
    ap.add_argument(
        "--build-only", action="store_true", help="build the label path and the variants, score nothing"
    )
    a = ap.parse_args()
    if a.from_json:
        text = report(json.loads(Path(a.from_json).read_text()))
        save_report(text, Path(a.out), f"{a.report_name}.md", a.report)
        print(text)
        return 0
    variants = [v for v in a.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; known: {list(VARIANTS)}")
    if a.quick:
        a.seeds, a.views, a.size, a.gs_steps, a.field_steps, a.target_views = "7", 24, "64x48", 300, 150, 2
        variants = variants[:2]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    standin, dino = Path(a.standin).resolve(), Path(a.standin_dino).resolve()
    rows, datas = [], []
    for seed in (int(s) for s in a.seeds.split(",")):
        data = out / f"scene-{seed}"
        label_pkg = out / "models" / f"s{seed}" / "manifest.json"
        if not label_pkg.is_file() and not a.no_build:
            build_scene(out, seed, a.views, a.size, a.gs_steps, a.field_steps, a.grad_threshold,
                        synth_flags(seed), preset="world")  # fmt: skip
        for v in variants if not a.no_build else ():
            clip_build(out, seed, data, v, a.field_steps, standin, dino, a.field_threads)
        if a.build_only:
            continue
        rows.append(score(out, seed, data, variants))
        datas.append(data)
        (out / "clip_path.json").write_text(json.dumps({"rows": rows}, indent=1, default=float))
    if a.build_only:
        return 0
    info = {**machine(), "date": time.strftime("%Y-%m-%d")}
    cmd = command_line("benchmarks.clip_path")
    if a.add_to:
        addition = {"command": cmd, "variants": variants, "machine": info}
        d = add_to(json.loads(Path(a.add_to).read_text()), rows, variants, addition)
        d["notes"] = [*d.get("notes", []), *a.note]
        d.update(segmenter_config(variants))
        from benchmarks.clip_targets import has_oracle_rows, rates

        # The table again (its candidates may have grown), with the oracle's rows if it had them or an
        # oracle variant is added.
        oracle = any(VARIANTS[v].get("oracle") for v in variants) or has_oracle_rows(d.get("target_maps", {}))
        d["target_maps"] = rates(
            [scene_targets(out, x, standin, dino, d["target_views"], oracle) for x in datas]
        )
        return write(d, out, a.report, a.report_name)
    from benchmarks.clip_targets import rates

    maps = (
        rates([scene_targets(out, x, standin, dino, a.target_views) for x in datas]) if a.target_views else {}
    )
    d = {
        "rows": rows,
        "variants": variants,
        "target_maps": maps,
        "target_views": a.target_views,
        "machine": info,
        "command": cmd,
        "standin": json.loads((standin / "standin.json").read_text()),
        "standin_dino": json.loads((dino / "standin_dino.json").read_text()),
        **segmenter_config(variants),
        "notes": a.note,
    }
    return write(d, out, a.report, a.report_name)


def write(d: dict, out: Path, committed: bool, name: str = "CLIP_PATH") -> int:
    """Store the figures ``d`` in OUT/clip_path.json and the report written from them in OUT/NAME.md;
    ``committed``: both into benchmarks/results/ too (NAME.json beside NAME.md,
    tests/benchmarks/test_clip_path_report.py)."""
    figures = json.dumps(d, indent=1, default=float)
    (out / "clip_path.json").write_text(figures)
    if committed:
        (ROOT / "benchmarks" / "results" / f"{name}.json").write_text(figures)
    text = report(json.loads(figures))  # the report is written from what is stored
    save_report(text, out, f"{name}.md", committed)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
