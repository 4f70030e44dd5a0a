"""Every setting of the build and training configs is a flag and a TOML key (fmgs/flags.py via fmgs.commands);
fewer steps compress a stage's schedule before the other settings apply; bad settings exit 2 naming them."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import pytest

from fmgs import cli
from fmgs.build.config import BuildConfig, TargetSpec
from fmgs.commands.build import build_config
from fmgs.commands.common import settings
from fmgs.commands.features import target_spec
from fmgs.commands.train_field import field_config
from fmgs.commands.train_gs import gs_config
from fmgs.train.config import FieldTrainConfig, GSTrainConfig


def _args(*argv: str):
    return cli.build_parser().parse_args(list(argv))


def test_build_flags_reach_every_stage_with_compressed_schedules():
    a = _args(
        *("build", "DATA", "--name", "toy", "--gs-steps", "1200", "--sh-degree", "0", "--grad-threshold"),
        *("0.001", "--gs-densify-reset-every", "333", "--targets", "labels", "--feature-scale", "0.5"),
        *("--field-steps", "600", "--field-select-opacity-min", "0.4", "--field-field-grid-levels", "8"),
        *("--seed", "3", "--device", "cpu"),
    )
    cfg = build_config(a)
    gs = GSTrainConfig.reduced(1200)
    assert cfg.gs == replace(
        gs, sh_degree=0, densify=replace(gs.densify, grad_threshold=0.001, reset_every=333)
    )
    assert cfg.targets == TargetSpec(kind="labels", feature_scale=0.5)
    fd = FieldTrainConfig().reduced(600)
    assert (
        cfg.field.steps == 600
        and cfg.field.dotsim_start == fd.dotsim_start != FieldTrainConfig().dotsim_start
    )
    assert cfg.field.select.opacity_min == 0.4 and cfg.field.field.grid.levels == 8 and cfg.field.seed == 3
    assert cfg.device == "cpu" and cfg.name == "toy"


def test_build_config_file_under_flags(tmp_path):
    f = tmp_path / "build.toml"
    f.write_text(
        'name = "fromfile"\nfield_dtype = "float16"\n[gs]\nsteps = 3000\nbackground = [0, 0, 0]\n'
        "[field]\nsteps = 2100\n[field.select]\nradius_min = 3.5\n[extra]\ndescription = 'x'\n"
    )
    cfg = build_config(_args("build", "DATA", "--config", str(f), "--field-steps", "1000", "--device", "cpu"))
    assert cfg.name == "fromfile" and cfg.field_dtype == "float16" and cfg.extra == {"description": "x"}
    assert cfg.gs == replace(GSTrainConfig.reduced(3000), background=(0.0, 0.0, 0.0))
    assert cfg.field.steps == 1000 and cfg.field.select.radius_min == 3.5  # the flag wins over the file
    assert cfg.field.dotsim_start == FieldTrainConfig().reduced(1000).dotsim_start


def test_a_schedule_compressed_to_its_own_length_is_the_default():
    assert GSTrainConfig.reduced(GSTrainConfig().steps) == GSTrainConfig()
    assert FieldTrainConfig().reduced(FieldTrainConfig().steps) == FieldTrainConfig()


def test_defaults_are_the_dataclasses():
    cfg = build_config(_args("build", "DATA", "--name", "n", "--device", "cpu"))
    assert cfg == BuildConfig(name="n")
    assert gs_config(_args("train-gs", "D", "--out", "O", "--device", "cpu")) == GSTrainConfig()
    tf = _args("train-field", "D", "--gaussians", "g", "--features", "f", "--out", "o", "--device", "cpu")
    assert field_config(tf) == FieldTrainConfig()
    assert target_spec(_args("features", "D", "--out", "O")) == TargetSpec()
    spec = target_spec(_args("features", "D", "--out", "O", "--feature-side", "640"))
    assert spec == TargetSpec(feature_side=640) and spec.feature_scale is None
    spec = target_spec(_args("features", "D", "--out", "O", "--feature-scale", "0.5"))
    assert spec.feature_scale == 0.5
    assert target_spec(_args("features", "D", "--out", "O", "--feature-scale", "none")) == TargetSpec()


def test_the_default_scale_blend_follows_the_dino_model():
    """DINO-weighted ("dominant") with a DINO model, the paper's mean without; either given is kept."""
    assert TargetSpec().scale_blend == "dominant"
    assert TargetSpec(dino_model=None).scale_blend == "mean"
    assert TargetSpec(scale_blend="mean").scale_blend == "mean"
    spec = target_spec(_args("features", "D", "--out", "O", "--dino-model", "none"))
    assert spec.dino_model is None and spec.scale_blend == "mean"
    with pytest.raises(ValueError, match="needs a dino_model"):
        TargetSpec(dino_model=None, scale_blend="dominant")


def test_train_gs_short_flags_and_tuples():
    cfg = gs_config(
        _args(
            "train-gs",
            "D",
            "--out",
            "O",
            "--steps",
            "500",
            "--scale",
            "0.5",
            "--background",
            "1,1,1",
            "--device",
            "cpu",
        )
    )
    assert cfg == replace(GSTrainConfig.reduced(500), image_scale=0.5, background=(1.0, 1.0, 1.0))
    with pytest.raises(SystemExit):
        _args("train-gs", "D", "--out", "O", "--background", "1,1")
    for bad in (("--background", "nan,1,1"), ("--lr-background", "nan")):  # NaN is no setting
        with pytest.raises(SystemExit):
            _args("train-gs", "D", "--out", "O", *bad)


@pytest.mark.parametrize(
    "toml, message",
    [
        ("[gs]\nstepz = 3\n", "unknown setting 'stepz'"),
        ("[gs]\nsteps = 'many'\n", "steps must be int"),
        ('name = "n"\n[targets]\nkind = "pixels"\n', "targets kind must be one of"),
        ('name = "n"\nfield_dtype = "int8"\n', "field_dtype must be one of"),
        ("[gs\n", "cannot read config file"),
        ('name = "n"\n[targets]\nscale_blend = "median"\n', "scale_blend must be one of"),
        ("[field]\nlr = nan\n", "field: lr must be a number, got nan"),  # NaN passed every range check
        ("[field.select]\nopacity_min = nan\n", "opacity_min must be a number, got nan"),
        # Out-of-range training settings were accepted (a negative count, a zero or negative rate).
        ("[gs]\nmax_init_points = -1\n", "GSTrainConfig: max_init_points must be > 0, got -1"),
        ("[gs]\nlr_means = 0.0\n", "lr_means must be > 0"),
        ("[gs.densify]\nrefine_every = 0\n", "DensifyConfig: refine_every must be > 0"),
        ("[field]\nlr = -1.0\n", "FieldTrainConfig: lr must be > 0, got -1.0"),
    ],
)
def test_bad_settings_exit_2_naming_the_setting(tmp_path, toml, message):
    f = tmp_path / "b.toml"
    f.write_text(toml)
    r = subprocess.run(
        [sys.executable, "-m", "fmgs.cli", "build", str(tmp_path), "--name", "n", "--config", str(f)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and message in r.stderr, r.stderr


def test_help_shows_each_default_from_its_dataclass():
    r = subprocess.run([sys.executable, "-m", "fmgs.cli", "build", "--help"], capture_output=True, text=True)
    assert r.returncode == 0
    text = " ".join(r.stdout.split())
    assert f"(default: {GSTrainConfig().densify.grad_threshold})" in text
    assert "--gs-densify-max-gaussians" in text and "--field-lam" in text
    assert TargetSpec().clip_model in "".join(r.stdout.split())  # help wraps long ids at hyphens


def test_sfm_settings_from_fmgs_sfm_and_fmgs_build():
    from fmgs.sfm.config import SfMConfig

    cfg = settings(
        _args("sfm", "IMGS", "--out", "O", "--camera-model", "OPENCV", "--max-image-size", "800"), SfMConfig
    )
    assert cfg == SfMConfig(camera_model="OPENCV", max_image_size=800)
    known = ("--camera-model", "PINHOLE", "--camera-params", "400,401.5,240,180", "--refine-principal-point")
    cfg = settings(
        _args("sfm", "I", "--out", "O", *known, "--no-refine-focal", "--intrinsics-file", "k.json"), SfMConfig
    )
    assert cfg == SfMConfig(
        camera_model="PINHOLE",
        camera_params=(400.0, 401.5, 240.0, 180.0),
        refine_principal_point=True,
        refine_focal=False,
        intrinsics_file="k.json",
    )
    b = build_config(
        _args(
            "build",
            "P",
            "--name",
            "n",
            "--sfm-matcher",
            "sequential",
            "--device",
            "cpu",
            "--no-sfm-refine-extra",
        )
    )
    assert b.sfm == SfMConfig(matcher="sequential", refine_extra=False)
    r = subprocess.run(
        [sys.executable, "-m", "fmgs.cli", "sfm", "IMGS", "--out", "O", "--camera-model", "FOO"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "camera_model must be one of" in r.stderr and "'FOO'" in r.stderr
    assert "'SIMPLE_RADIAL'" in r.stderr and "Traceback" not in r.stderr


def test_every_listed_camera_model_is_colmaps_with_its_parameters():
    import pycolmap

    from fmgs.sfm.config import CAMERA_PARAMS

    for model, params in CAMERA_PARAMS.items():
        cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, 10, 10)
        assert cam.params_info.replace(" ", "") == params
