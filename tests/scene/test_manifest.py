"""fmgs.scene.manifest: one typed reader and writer; every malformed key is refused with its name."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fmgs.errors import ValidationError
from fmgs.scene.manifest import CANONICAL_PHRASES, FieldInfo, Manifest


def _manifest(**kw) -> Manifest:
    base = dict(
        name="s",
        encoder_id="enc",
        dim=6,
        canonical=CANONICAL_PHRASES,
        num_gaussians=40,
        num_selected=20,
        sh_degree=1,
        bounds=(0.0, 0, 0, 1, 1, 1),
        field=FieldInfo({"grid": {}}, {"lo": [0, 0, 0]}, False, "float16"),
        extra={"label_names": ["a", "b"], "note": 1},
    )
    return Manifest(**{**base, **kw})


def test_round_trip_and_label_names(tmp_path):
    m = _manifest()
    m.write(tmp_path)
    back = Manifest.read(tmp_path)
    assert back == m and back.label_names == ("a", "b")
    raw = json.loads((tmp_path / "manifest.json").read_text())
    assert (
        raw["format"] == "fmgs.scene"
        and raw["version"] == 1
        and raw["counts"] == {"gaussians": 40, "selected": 20}
    )
    assert _manifest(extra={}).label_names == ()


def _edited(tmp_path, edit) -> None:
    _manifest().write(tmp_path)
    raw = json.loads((tmp_path / "manifest.json").read_text())
    edit(raw)
    (tmp_path / "manifest.json").write_text(json.dumps(raw))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda m: m.update(format="x"), "not an fmgs.scene manifest"),
        (lambda m: m.update(version=2), "unsupported version 2"),
        (lambda m: m.pop("counts"), "missing key 'counts'"),
        (lambda m: m.update(encoder={"id": "e", "dim": "6"}), "encoder must be"),
        (lambda m: m.update(encoder={"id": "e", "dim": True}), "encoder must be"),
        (lambda m: m.update(counts={"gaussians": 1}), "counts must be"),
        (lambda m: m.update(canonical="object"), "canonical must be a list"),
        (lambda m: m.update(bounds=[0, 0]), "bounds must be 6 finite numbers"),
        (lambda m: m.update(bounds=[float("nan"), 0, 0, 1, 1, 1]), "bounds must be 6 finite numbers"),
        (lambda m: m.update(bounds=[0, 0, 0, float("inf"), 1, 1]), "bounds must be 6 finite numbers"),
        (lambda m: m.update(bounds=[0, 0, 0, 10**400, 1, 1]), "bounds must be 6 finite numbers"),
        (lambda m: m.update(sh_degree=7), "sh_degree"),
        (lambda m: m.update(extra=[1]), "extra must be an object"),
        (lambda m: m.update(field={"config": 1}), "field must be"),
        (lambda m: m["field"].update(dtype="int8"), "field dtype 'int8'"),
        (lambda m: m.update(name=3), "name must be a string"),
    ],
)
def test_malformed_manifests_name_what_is_wrong(tmp_path, edit, message):
    _edited(tmp_path, edit)
    with pytest.raises(ValidationError, match=message) as e:
        Manifest.read(tmp_path)
    assert str(tmp_path / "manifest.json") in str(e.value)


def test_missing_and_unreadable(tmp_path):
    with pytest.raises(ValidationError, match=r"no manifest\.json"):
        Manifest.read(tmp_path)
    (tmp_path / "manifest.json").write_bytes(b"\xff{")
    with pytest.raises(ValidationError, match="unreadable manifest"):
        Manifest.read(tmp_path)


def test_older_manifests_without_optional_keys_read_with_defaults(tmp_path):
    _edited(tmp_path, lambda m: [m.pop(k) for k in ("sh_degree", "bounds", "extra", "embedding_dtype")])
    m = Manifest.read(tmp_path)
    assert m.sh_degree == 0 and m.bounds == (0.0,) * 6 and m.extra == {} and m.embedding_dtype == "float16"
    _edited(tmp_path, lambda m: m["field"].pop("dtype"))
    assert Manifest.read(tmp_path).field.dtype == "float32"


def test_reading_a_manifest_imports_no_torch():
    code = "import sys, fmgs.scene.manifest; print('torch' in sys.modules)"
    assert (
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        ).stdout.strip()
        == "False"
    )
