"""Package faces resolve their exports on first use (fmgs.lazy), and the config and manifest modules that
commands and servers read at start import no torch."""

from __future__ import annotations

import importlib
import importlib.util
import subprocess
import sys

import pytest

from fmgs.lazy import lazy_exports


@pytest.mark.parametrize("package", ["fmgs", "fmgs.query", "fmgs.features", "fmgs.build", "fmgs.sfm"])
def test_every_export_is_its_module_attribute(package):
    mod = importlib.import_module(package)
    assert mod.__all__ and sorted(mod.__all__) == sorted(mod._EXPORTS)
    for name in mod.__all__:
        assert getattr(mod, name) is getattr(importlib.import_module(mod._EXPORTS[name]), name), name
    with pytest.raises(AttributeError, match=f"module '{package}' has no attribute 'nope'"):
        mod.nope  # noqa: B018
    # An export named like a submodule would turn into that module once the submodule is imported.
    clash = [n for n in mod.__all__ if importlib.util.find_spec(f"{package}.{n}") is not None]
    assert clash == [], clash


def test_lazy_exports_import_on_first_use_only():
    get = lazy_exports("pkg", {"dumps": "json", "missing": "no_such_module_here"})
    assert get("dumps") is importlib.import_module("json").dumps
    with pytest.raises(ModuleNotFoundError):
        get("missing")
    with pytest.raises(AttributeError, match="module 'pkg' has no attribute 'other'"):
        get("other")


def test_light_modules_import_no_torch():
    mods = (
        "fmgs fmgs.query fmgs.features fmgs.flags fmgs.cli fmgs.build fmgs.build.config fmgs.sfm "
        "fmgs.sfm.config fmgs.train.config fmgs.field.config fmgs.query.config fmgs.scene.manifest "
        "fmgs.features.models"
    ).split()
    code = (
        f"import sys\nfor m in {mods!r}: __import__(m)\nprint(sorted(m for m in sys.modules if m == 'torch'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
