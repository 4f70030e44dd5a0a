"""The committed CLIP-path report (benchmarks/results/CLIP_PATH.md) is written from its committed figures
(CLIP_PATH.json) by the report writer, and the figures docs/field.md and docs/limits.md quote are those
figures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.clip_path import report, summary

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"


def _figures() -> dict:
    return json.loads((RESULTS / "CLIP_PATH.json").read_text())


@pytest.mark.parametrize(
    "name",
    ["CLIP_PATH", "CLIP_PATH_POOLED", "CLIP_PATH_ORACLE_PAPER", "CLIP_PATH_NEIGHBOURS", "CLIP_PATH_FINER"],
)
def test_committed_report_is_written_from_the_committed_figures(name):
    d = json.loads((RESULTS / f"{name}.json").read_text())
    assert report(d) == (RESULTS / f"{name}.md").read_text()


@pytest.mark.parametrize(
    "name,kinds",
    [
        ("CLIP_PATH_POOLED", ("labels", "dominant", "dominant pooled")),
        ("CLIP_PATH_ORACLE_PAPER", ("labels", "dominant", "oracle paper")),
        ("CLIP_PATH_NEIGHBOURS", ("labels", "dominant", "dominant neighbours 1", "labels neighbours 1")),
    ],
)
def test_docs_quote_the_comparisons_on_the_pooled_label_builds(name, kinds):
    """docs/field.md's figures for each comparison made on CLIP_PATH_POOLED's label builds (DINO-coherent
    pooling, the paper's mean named without error, one embedding per Gaussian) are its report's, beside
    the default built on the same ones."""
    d = json.loads((RESULTS / f"{name}.json").read_text())
    docs = (ROOT / "docs" / "field.md").read_text()
    for kind in kinds:
        s = summary(d["rows"], kind)
        assert s["scenes"] == 3, kind  # the docs quote the three seeds' means
        keys = ["miou", "localisation_2d", "localisation_3d"] + (["novel_3d"] if "neighbours" in name else [])
        for key in keys:
            assert f"{s[key]:.3f}" in docs, (kind, key, s[key])


def test_docs_quote_the_reports_figures():
    d = _figures()
    docs = (ROOT / "docs" / "field.md").read_text() + (ROOT / "docs" / "limits.md").read_text()
    for kind in (
        "labels",
        "paper",
        "dominant",
        "paper no-DINO",
        "region crops",
        "dominant 4200 steps",
        "lifted",
        "segments finest label masks",
    ):
        s = summary(d["rows"], kind)
        for key in ("miou", "localisation_2d", "localisation_3d"):
            assert f"{s[key]:.3f}" in docs, (kind, key, s[key])


def test_committed_target_report_is_written_from_its_figures_and_backs_the_default():
    """CLIP_TARGETS.md (the dev scenes the default blend was chosen on) renders from CLIP_TARGETS.json, and
    the default blend is the best there on object pixels among the blends the build offers."""
    from benchmarks.clip_targets import report as targets_report
    from fmgs.features.sizes import SCALE_BLEND, SCALE_BLENDS

    d = json.loads((RESULTS / "CLIP_TARGETS.json").read_text())
    assert targets_report(d) == (RESULTS / "CLIP_TARGETS.md").read_text()
    best = max(SCALE_BLENDS, key=lambda b: d["rates"][b]["object_pixels"])
    assert best == SCALE_BLEND


def test_an_added_variant_joins_every_table_and_its_label_builds_are_shown():
    """``--add-to``: a variant scored on label builds made again joins the stored rows of its seeds; the
    report lists it in every table and shows both label builds per seed."""
    import copy

    from benchmarks.clip_path import REFIT, add_to

    d = _figures()
    d["variants"] = [v for v in d["variants"] if v != "oracle"]
    for r in d["rows"]:  # as before any addition
        r.pop("refit_labels", None)
        r.pop("refit_variants", None)
        r["kinds"].pop("oracle", None)
    new_rows = []
    for r in d["rows"]:
        labels = copy.deepcopy(r["kinds"]["labels"])
        labels["miou"] = 0.5  # the label build made again scored otherwise
        new_rows.append({"seed": r["seed"], "kinds": {"labels": labels, "oracle": r["kinds"]["dominant"]}})
    machine = {**d["machine"], "date": "2099-01-01"}
    merged = add_to(
        copy.deepcopy(d), new_rows, ["oracle"], {"command": "cmd", "machine": machine, "variants": ["oracle"]}
    )
    text = report(merged)
    assert merged["variants"][-1] == "oracle" and summary(merged["rows"], "oracle")["scenes"] == len(
        d["rows"]
    )
    assert "Added 2099-01-01" in text and REFIT in text
    assert sum(line.startswith("| oracle |") for line in text.splitlines()) == 3  # means, quorum, held-out
    for r in d["rows"]:
        assert f"| {r['seed']} | labels | made again | " in text and f"| {r['seed']} | oracle | " in text
    assert "| 0.500 |" in text
    with pytest.raises(ValueError, match="no new scores"):
        add_to(
            copy.deepcopy(d), new_rows[:1], ["oracle"], {"command": "cmd", "machine": machine, "variants": []}
        )


def test_a_variant_built_again_keeps_its_rows_and_is_shown_beside_them():
    """``--add-to`` with a variant the report holds: its stored rows stay in the tables, the new build is
    shown beside them per seed; a later addition on other label builds is refused."""
    import copy

    from benchmarks.clip_path import add_to

    d = _figures()
    new_rows = []
    for r in d["rows"]:
        again = copy.deepcopy(r["kinds"]["dominant"])
        again["miou"] = 0.123  # the default built again scored otherwise
        labels = r.get("refit_labels", r["kinds"]["labels"])  # the label builds of earlier additions
        new_rows.append({"seed": r["seed"], "kinds": {"labels": labels, "dominant": again}})
    add = {"command": "cmd", "machine": {**d["machine"], "date": "2099-01-01"}, "variants": ["dominant"]}
    merged = add_to(copy.deepcopy(d), new_rows, ["dominant"], add)
    text = report(merged)
    assert merged["variants"] == d["variants"]
    assert summary(merged["rows"], "dominant") == summary(d["rows"], "dominant")
    for r in d["rows"]:
        assert f"| {r['seed']} | dominant | in the tables | " in text
        assert f"| {r['seed']} | dominant | made again | " in text
    assert "| 0.123 |" in text
    other = copy.deepcopy(new_rows)
    other[0]["kinds"]["labels"] = {**other[0]["kinds"]["labels"], "miou": 0.5}
    with pytest.raises(ValueError, match="label build differs"):
        add_to(merged, other, ["dominant"], add)


def test_presence_docs_quote_the_rules_on_the_kept_builds():
    """docs/presence.md's figures for the served rule (the mean) and the rule before it are the report's,
    on the builds scored with both (the label builds and the default made again)."""
    from benchmarks.clip_path import rule_rates

    rows = _figures()["rows"]
    labels = [r["refit_labels"] for r in rows]
    default = [r["refit_variants"]["dominant"] for r in rows]
    docs = (ROOT / "docs" / "presence.md").read_text()
    lm, lb = rule_rates(labels, "presence_mean"), rule_rates(labels, "presence_best")
    dm, db = rule_rates(default, "presence_mean"), rule_rates(default, "presence_best")
    for x in (dm["presence"], db["presence"], dm["absent_rejected"], db["absent_rejected"], lm["presence"]):
        assert f"{x:.3f}" in docs, x
    assert dm["present_found"] == db["present_found"] and f"presents found {dm['present_found']:.3f}" in docs
    assert f"({dm['presence']:.3f} against {lm['presence']:.3f}, from {db['presence']:.3f} against " in docs
    assert f"{lb['presence']:.3f})" in docs and lm["presence"] - dm["presence"] > 0.05  # docs: "wider than 5"
    assert dm["presence"] > db["presence"] and dm["absent_rejected"] > db["absent_rejected"]


def test_a_variant_of_another_variants_targets_distils_its_cache_at_its_own_steps(tmp_path, monkeypatch):
    """A "features_of" variant runs ``fmgs train-field`` on that variant's feature cache (the same targets,
    no extraction) at its own field steps, whatever the run's; without the cache it says which to build."""
    import fmgs.cli
    from benchmarks.clip_variants import STANDIN, STANDIN_DINO, VARIANTS, clip_build
    from fmgs.train.config import FieldTrainConfig

    calls: list[list[str]] = []
    monkeypatch.setattr(fmgs.cli, "main", lambda cmd: calls.append(cmd) or 0)
    v = next(k for k, x in VARIANTS.items() if x.get("features_of") == "dominant")
    data = tmp_path / "scene-7"
    with pytest.raises(FileNotFoundError, match="build 'dominant' first"):
        clip_build(tmp_path, 7, data, v, 1500, STANDIN, STANDIN_DINO, 1)
    assert calls == []
    cache = tmp_path / "models" / ".work" / "s7-dominant" / "features"
    cache.mkdir(parents=True)
    pkg = clip_build(tmp_path, 7, data, v, 1500, STANDIN, STANDIN_DINO, 1)
    (cmd,) = calls
    assert cmd[:2] == ["train-field", str(data)]
    assert cmd[cmd.index("--features") + 1] == str(cache)
    assert cmd[cmd.index("--package") + 1] == str(pkg)
    assert cmd[cmd.index("--field-steps") + 1] == str(FieldTrainConfig.steps) != "1500"
    assert cmd[cmd.index("--threads") + 1] == "1"
    clip_build(tmp_path, 7, data, v, 1500, STANDIN, STANDIN_DINO, 1)  # recorded: not run again
    assert len(calls) == 1


def test_label_mask_variants_make_their_cache_then_distil_it_with_their_loss(tmp_path, monkeypatch):
    """ "segments finest label masks" writes benchmarks.label_segments' cache, then ``fmgs train-field``
    distils it; the variants on its cache keep the targets and change only the loss: ``--balance scale``,
    or the language loss alone (``--lam 1``, no dotsim)."""
    import benchmarks.label_segments
    import fmgs.cli
    from benchmarks.clip_variants import STANDIN, STANDIN_DINO, clip_build

    calls: list[list[str]] = []
    monkeypatch.setattr(fmgs.cli, "main", lambda cmd: calls.append(cmd) or 0)
    made: list[tuple] = []

    def cache(data, cache_dir, standin, dino, segment_map):
        cache_dir.mkdir(parents=True)
        made.append((cache_dir, segment_map))

    monkeypatch.setattr(benchmarks.label_segments, "label_segments_cache", cache)
    data = tmp_path / "scene-7"
    clip_build(tmp_path, 7, data, "segments finest label masks", 1500, STANDIN, STANDIN_DINO, 1)
    features = tmp_path / "models" / ".work" / "s7-segments-finest-label-masks" / "features"
    assert made == [(features, "finest")]
    for variant, flags, absent in (
        ("segments finest label masks", [], ["--balance", "--lam", "--no-dotsim"]),
        ("segments finest label masks balanced", ["--balance", "scale"], ["--lam", "--no-dotsim"]),
        ("segments finest label masks no-DINO", ["--lam", "1", "--no-dotsim"], ["--balance"]),
    ):
        if variant != "segments finest label masks":
            clip_build(tmp_path, 7, data, variant, 1500, STANDIN, STANDIN_DINO, 1)
        cmd = calls[-1]
        assert cmd[0] == "train-field" and cmd[cmd.index("--features") + 1] == str(features), variant
        text = " ".join(cmd)
        assert " ".join(flags) in text and not any(f in cmd for f in absent), variant
    assert len(calls) == 3 and len(made) == 1


def test_photos_variant_cuts_its_crops_from_the_scene_generated_again_larger(tmp_path, monkeypatch):
    """ "dominant photos x2" builds from the scene generated again at twice the width and height (the same
    poses and objects), its maps stored at the scene's own size; a folder that shows another scene is
    refused, not used."""
    import fmgs.cli
    from benchmarks.clip_variants import STANDIN, STANDIN_DINO, clip_build, photos_scene

    real = fmgs.cli.main
    data = tmp_path / "scene-7"
    synth = [
        "synth",
        "--preset",
        "world",
        "--objects",
        "3",
        "--views",
        "4",
        "--size",
        "32x24",
        "--novel",
        "1",
    ]
    assert real([*synth, "--out", str(data), "--seed", "7"]) == 0
    calls: list[list[str]] = []
    monkeypatch.setattr(
        fmgs.cli, "main", lambda cmd: calls.append(cmd) or (real(cmd) if cmd[0] == "synth" else 0)
    )
    clip_build(tmp_path, 7, data, "dominant photos x2", 1500, STANDIN, STANDIN_DINO, 1)
    photos = tmp_path / "scene-7-x2"
    assert [c[0] for c in calls] == ["synth", "build"]
    build = calls[-1]
    assert build[1] == str(photos) and build[build.index("--feature-side") + 1] == "32"
    assert build[build.index("--scale-blend") + 1] == "dominant"
    t0, t1 = (json.loads((d / "transforms.json").read_text()) for d in (data, photos))
    assert (t1["w"], t1["h"]) == (64, 48) and t1["fl_x"] == 2 * t0["fl_x"]
    assert [f["transform_matrix"] for f in t1["frames"]] == [f["transform_matrix"] for f in t0["frames"]]
    assert "--crop-scales" not in build
    # The finer variant: the same larger scene (not generated again), one finer scale before the pyramid's.
    clip_build(tmp_path, 7, data, "dominant finer photos x2", 1500, STANDIN, STANDIN_DINO, 1)
    from fmgs.commands.build import build_config
    from fmgs.features.sizes import CROP_SCALES

    assert [c[0] for c in calls] == ["synth", "build", "build"] and calls[-1][1] == str(photos)
    cfg = build_config(fmgs.cli.build_parser().parse_args([*calls[-1], "--device", "cpu"]))
    assert cfg.targets.crop_scales == (CROP_SCALES[0] / 2, *CROP_SCALES)
    other = tmp_path / "other"
    assert real([*synth, "--out", str(other), "--seed", "8", "--size", "64x48"]) == 0
    with pytest.raises(ValueError, match="does not show"):
        photos_scene(data, other, 2)


def test_the_label_paths_targets_distil_again_from_the_label_builds_cache(tmp_path, monkeypatch):
    """ "labels 4200 steps" runs ``fmgs train-field`` on the label build's own cache (OUT/models/.work/sSEED),
    language loss alone, at the product's field steps."""
    import fmgs.cli
    from benchmarks.clip_variants import STANDIN, STANDIN_DINO, clip_build
    from fmgs.train.config import FieldTrainConfig

    calls: list[list[str]] = []
    monkeypatch.setattr(fmgs.cli, "main", lambda cmd: calls.append(cmd) or 0)
    cache = tmp_path / "models" / ".work" / "s7" / "features"
    cache.mkdir(parents=True)
    clip_build(tmp_path, 7, tmp_path / "scene-7", "labels 4200 steps", 1500, STANDIN, STANDIN_DINO, 1)
    (cmd,) = calls
    assert cmd[0] == "train-field" and cmd[cmd.index("--features") + 1] == str(cache)
    assert cmd[cmd.index("--gaussians") + 1] == str(
        tmp_path / "models" / ".work" / "s7" / "gs" / "point_cloud.ply"
    )
    assert cmd[cmd.index("--field-steps") + 1] == str(FieldTrainConfig.steps)
    assert cmd[cmd.index("--lam") + 1] == "1" and "--no-dotsim" in cmd


@pytest.mark.parametrize(
    "variant,source", [("dominant neighbours 1", "s7-dominant"), ("labels neighbours 1", "s7")]
)
def test_a_neighbours_variant_packages_its_sources_field_again(tmp_path, monkeypatch, variant, source):
    """A "neighbours" variant trains nothing: its source's package is packaged again with that many
    embedding neighbours and the source's text encoder, and its build time is the source's and the
    packaging's; without the source it says which to build."""
    import benchmarks.unseen
    from benchmarks.clip_variants import STANDIN, STANDIN_DINO, clip_build
    from fmgs.features.models import MINILM_ID

    calls: list[tuple] = []
    monkeypatch.setattr(
        benchmarks.unseen, "repackage", lambda src, dst, k, enc: calls.append((src, dst, k, enc.id)) or dst
    )
    data, models = tmp_path / "scene-7", tmp_path / "models"
    (models / ".work" / source / "features").mkdir(parents=True)  # a features_of variant's check
    with pytest.raises(FileNotFoundError, match=f"needs {models / source}"):
        clip_build(tmp_path, 7, data, variant, 1500, STANDIN, STANDIN_DINO, 1)
    (models / source).mkdir()
    (models / source / "manifest.json").write_text(json.dumps({"encoder": {"id": MINILM_ID, "dim": 384}}))
    record = tmp_path / ("build-7.json" if source == "s7" else f"build-{source}.json")
    record.write_text(json.dumps({"seconds": 1000.0, "command": []}))
    pkg = clip_build(tmp_path, 7, data, variant, 1500, STANDIN, STANDIN_DINO, 1)
    assert calls == [(models / source, pkg, 1, MINILM_ID)]
    took = json.loads((tmp_path / f"build-{pkg.name}.json").read_text())["seconds"]
    assert 1000.0 < took < 1000.0 + 60
    clip_build(tmp_path, 7, data, variant, 1500, STANDIN, STANDIN_DINO, 1)  # recorded: not run again
    assert len(calls) == 1


def test_a_report_on_scenes_another_holds_leaves_the_target_table_out():
    """``--target-views 0``: the target maps depend on the scenes alone, so a comparison on another report's
    scenes writes every build table and no target table."""
    d = _figures()
    full = report(d)
    d["target_maps"] = {}
    text = report(d)
    assert "## The targets alone, before distillation" in full
    assert "## The targets alone" not in text and "## Means over the scenes" in text
