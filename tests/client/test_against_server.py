"""The thin client against the real server on port 0 (three-blob scenes, a fake text encoder)."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess

import numpy as np
import pytest

from fmgs.query.engine import SceneEngine
from fmgs.query.presence import negative_names, probes
from fmgs_client import cli
from fmgs_client.client import FmgsClient, FmgsError
from fmgs_client.ply import read_ply
from fmgs_client.types import CameraSpec, Presence
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.images import decode_png
from tests.helpers.query_scenes import CENTRES, CLASS_NAMES, ENCODER_ID, FakeEncoder, blob_scene


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("client") / "models"
    root.mkdir()
    blob_scene(root / "blobs", with_field=True)
    blob_scene(root / "plain", seed=1)
    return root


def _start(models, **kw):
    kw.setdefault("reload_check_s", 0.0)
    return start_server(ServerConfig(models=models, port=0, **kw), encoder_factory=lambda i: FakeEncoder())


@pytest.fixture(scope="module")
def server(models):
    srv = _start(models, chunk_bytes=512)  # small chunks: every answer arrives in pieces
    yield srv
    srv.stop(0)


@pytest.fixture()
def client(server):
    with FmgsClient(server.address, timeout=30) as c:
        yield c


def _cam(w: int = 48, h: int = 40) -> CameraSpec:
    """Looks down +z from the origin at the blobs (as the server tests' camera)."""
    return CameraSpec(np.eye(4), 40.0, 40.0, w / 2, h / 2, w, h)


def test_scenes(client):
    scenes = client.list_scenes()
    assert [s.name for s in scenes] == ["blobs", "plain"]
    info = client.scene("blobs")
    assert info.encoder_id == ENCODER_ID and info.num_gaussians == 180 and info.has_field
    assert info.label_names == CLASS_NAMES and len(info.canonical_phrases) == 4
    assert info.state == "unloaded" and info.resident_bytes == 0  # scenes load on first use
    assert info.bounds.shape == (2, 3)  # from the manifest, before loading
    client.query("blobs", "red cube", top_k=1)
    info = client.scene("blobs")
    assert info.state == "ready" and info.resident_bytes > 0
    assert info.bounds.shape == (2, 3) and np.all(info.bounds[0] <= info.bounds[1])
    with pytest.raises(FmgsError) as e:
        client.scene("nope")
    assert e.value.code == "NOT_FOUND"
    assert client.health() == "SERVING" and client.health("fmgs.v1.Fmgs") == "SERVING"


def test_query_matches_engine(client, models):
    answers = client.query(
        "blobs",
        list(CLASS_NAMES),
        top_k=60,
        fields=["mean", "similarity", "opacity", "scale", "rotation", "color"],
        instances={"min_points": 5},
    )
    eng = SceneEngine.open(models / "blobs")
    vecs = FakeEncoder().encode_text(list(CLASS_NAMES))
    for k, (a, name) in enumerate(zip(answers, CLASS_NAMES, strict=True)):
        ref = eng.text_query(vecs[k], 60)
        assert a.text == name and len(a) == 60
        np.testing.assert_array_equal(a.index, ref.index.numpy())
        np.testing.assert_allclose(a.relevancy, ref.relevancy.numpy(), rtol=1e-6)
        np.testing.assert_allclose(a.mean, eng.gaussians.means[ref.index].numpy(), rtol=1e-6)
        assert a.scale.shape == (60, 3) and a.rotation.shape == (60, 4) and a.color.shape == (60, 3)
        np.testing.assert_allclose(np.linalg.norm(a.rotation, axis=1), 1, atol=1e-5)
        assert a.instance.dtype == np.int32 and a.instances
        top = a.instances[0]
        assert np.linalg.norm(top.centroid - CENTRES[k].numpy()) < 0.2
        assert np.all(np.abs(top.aabb.center - top.centroid) < top.aabb.extent)
        assert (a.instance == top.id).sum() == top.num_members
    # Presence as the engine computes it with the scene's negatives (vocabulary and label names).
    # Texts naming a colour are decided with their colour contrasts too.
    names = negative_names(eng.manifest.label_names)
    enc = FakeEncoder()
    negs = enc.encode_text(names)
    texts = [*CLASS_NAMES, "laptop", "giraffe", "green cube"]
    got = client.query("blobs", texts, top_k=3)
    vecs_t = enc.encode_text(texts)
    for a, text, v, pr in zip(got, texts, vecs_t, probes(texts, vecs_t, enc.encode_text), strict=True):
        p = eng.text_query(v, 3, negatives=negs, probe=pr).presence
        rivals = [*names, *pr.names]
        assert a.presence == Presence(p.score, p.found, p.margin, rivals[p.rival]) and a.found == p.found
        assert a.found == (text in CLASS_NAMES)
    # Precomputed embeddings instead of texts.
    emb = vecs.numpy().astype(np.float32)
    again = client.query("blobs", ["x", "y", "z"], top_k=5, embeddings=emb, encoder_id=ENCODER_ID)
    np.testing.assert_array_equal(again[1].index, answers[1].index[:5])
    with pytest.raises(FmgsError) as e:
        client.query("blobs", "a", embeddings=emb[:1], encoder_id="other/enc")
    assert e.value.code == "FAILED_PRECONDITION"


@pytest.mark.parametrize("rule", [{"rule": "each", "quorum": 40}, {"rule": "each"}, {"pool": 40}])
def test_the_presence_rule_is_the_servers_setting(models, rule):
    """--presence-rule, --presence-quorum and --presence-pool reach the engine: presence as
    PresenceConfig(...) decides it (the default rule, the mean of 10, in the module's other tests)."""
    from fmgs.query.presence import PresenceConfig

    eng = SceneEngine.open(models / "blobs")
    enc = FakeEncoder()
    names = negative_names(eng.manifest.label_names)
    negs = enc.encode_text(names)
    texts = [*CLASS_NAMES, "giraffe"]
    vecs = enc.encode_text(texts)
    srv = _start(models, **{f"presence_{k}": v for k, v in rule.items()})
    try:
        with FmgsClient(srv.address, timeout=30) as c:
            got = c.query("blobs", texts, top_k=3)
    finally:
        srv.stop(0)
    margins = []
    for a, v, pr in zip(got, vecs, probes(texts, vecs, enc.encode_text), strict=True):
        p = eng.text_query(v, 3, negatives=negs, probe=pr, presence_cfg=PresenceConfig(**rule)).presence
        mean = eng.text_query(v, 3, negatives=negs, probe=pr).presence  # the default
        assert a.presence.margin == p.margin and a.found == p.found
        margins.append((p.margin, mean.margin))
    assert any(m != m1 for m, m1 in margins)  # the rule made a difference somewhere
    with pytest.raises(ValueError, match="presence_quorum"):
        ServerConfig(models=models, presence_quorum=0).validate()
    with pytest.raises(ValueError, match="presence_pool"):
        ServerConfig(models=models, presence_pool=0).validate()
    with pytest.raises(ValueError, match="presence_pool must be <= 64"):
        ServerConfig(models=models, presence_pool=65).validate()
    with pytest.raises(ValueError, match="presence_rule must be one of"):
        ServerConfig(models=models, presence_rule="max").validate()
    with pytest.raises(ValueError, match="presence_quorum needs presence_rule 'each'"):
        ServerConfig(models=models, presence_quorum=4).validate()


def test_render_float_and_png(client):
    cam = _cam()
    r = client.render("blobs", cam, "green ball", outputs=("relevancy", "rgb", "depth", "alpha"))
    assert r.relevancy.shape == (40, 48) and r.rgb.shape == (40, 48, 3) and r.alpha.shape == (40, 48)
    assert r.relevancy[r.argmax.y, r.argmax.x] == pytest.approx(r.argmax.value, rel=1e-5)
    # The green ball sits at +x: its most relevant pixel is right of the centre.
    assert r.argmax.x > 24
    p = client.render("blobs", cam, "green ball", outputs=("relevancy", "rgb", "depth"), encoding="png")
    assert set(p.png) >= {"relevancy", "rgb", "depth"}
    np.testing.assert_allclose(p.relevancy, r.relevancy, atol=1 / 255)
    np.testing.assert_allclose(p.rgb, np.clip(r.rgb, 0, 1), atol=1 / 255)
    np.testing.assert_allclose(p.depth, r.depth, atol=1e-3)
    with pytest.raises(FmgsError) as e:
        client.render("blobs", cam, "")
    assert e.value.code == "INVALID_ARGUMENT"


def test_stream(client):
    cams = [_cam(32, 24) for _ in range(20)]
    got = list(client.stream("blobs", iter(cams), "red cube"))
    seqs = [r.sequence for r in got]
    assert seqs and seqs == sorted(seqs) and seqs[-1] == 19  # the newest pose is always answered
    assert all(r.relevancy.shape == (24, 32) for r in got)
    # Leaving early cancels the call without an error.
    for _ in client.stream("blobs", iter(cams), "red cube"):
        break


def test_points_and_segment(client):
    pts = CENTRES[:2].numpy()
    p = client.points("blobs", ["red cube", "green ball"], pts)
    assert p.relevancy.shape == (2, 2) and np.isfinite(p.similarity).all()
    s = client.segment("blobs", list(CLASS_NAMES), camera=_cam())
    assert s.pixel_labels.shape == (40, 48) and s.class_names == CLASS_NAMES
    assert (s.gaussian_labels == s.gaussian_index // 60).mean() > 0.9
    with pytest.raises(FmgsError) as e:
        client.points("plain", "a", pts)
    assert e.value.code == "FAILED_PRECONDITION"


def test_admin_and_tokens(models, tmp_path):
    (tmp_path / "read").write_text("reader\n")
    (tmp_path / "admin").write_text("boss\n")
    srv = _start(models, token_file=tmp_path / "read", admin_token_file=tmp_path / "admin")
    try:
        with FmgsClient(srv.address) as anon, pytest.raises(FmgsError) as e:
            anon.list_scenes()
        assert e.value.code == "UNAUTHENTICATED"
        with FmgsClient(srv.address, token="reader") as c:
            assert len(c.list_scenes()) == 2
            with pytest.raises(FmgsError) as e:
                c.load("blobs")
            assert e.value.code == "PERMISSION_DENIED"
        with FmgsClient(srv.address, token="boss") as c:
            assert c.load("blobs").state == "ready"
            assert c.reload("blobs").state == "ready"
            assert c.unload("blobs").state == "unloaded"
        (tmp_path / "tok").write_text("reader\n")
        assert cli.main(["--address", srv.address, "--token-file", str(tmp_path / "tok"), "list"]) == 0
        assert cli.main(["--address", srv.address, "list"]) == 1
    finally:
        srv.stop(0)


def test_cli(server, tmp_path, capsys):
    base = ["--address", server.address]
    assert cli.main([*base, "info", "blobs"]) == 0
    assert "test/blob-encoder" in capsys.readouterr().out
    ply = tmp_path / "q.ply"
    assert (
        cli.main([*base, "query", "blobs", "red cube", "--top-k", "60", "--instances", "--ply", str(ply)])
        == 0
    )
    out = capsys.readouterr().out
    assert "'red cube': 60 Gaussians" in out and "instances:" in out and ": found" in out
    assert cli.main([*base, "query", "blobs", "laptop", "--top-k", "3"]) == 0
    out = capsys.readouterr().out
    assert "NOT FOUND (the scene has '" in out and "'laptop': 3 Gaussians" in out
    pc = read_ply(ply)
    assert pc.points.shape == (60, 3)
    assert np.mean(np.linalg.norm(pc.points - CENTRES[0].numpy(), axis=1) < 0.5) > 0.9  # mostly the red cube
    # The default camera looks at the bounds' centre from outside: all three blobs are in view.
    png = tmp_path / "r.png"
    assert cli.main([*base, "render", "blobs", "blue cone", "--size", "64x48", "--out", str(png)]) == 0
    assert "argmax pixel" in capsys.readouterr().out
    assert decode_png(png.read_bytes()).shape == (48, 64, 3)
    assert (
        cli.main(
            [*base, "segment", "blobs", *CLASS_NAMES, "--size", "32x24", "--out", str(tmp_path / "s.png")]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert all(name in out for name in CLASS_NAMES)
    labels = decode_png((tmp_path / "s.png").read_bytes())
    assert len(np.unique(labels.reshape(-1, 3), axis=0)) >= 3  # background and at least two classes seen
    assert cli.main([*base, "stream", "blobs", "red cube", "--frames", "8", "--size", "32x24"]) == 0
    assert "frames/s" in capsys.readouterr().out
    assert cli.main([*base, "query", "nope", "a"]) == 1
    assert capsys.readouterr().err.startswith("error: NOT_FOUND: ")


def _json_lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def test_cli_json(server, client, tmp_path, capsys):
    """--json: one object per answer, the same answer the library gets."""
    base = ["--address", server.address]
    assert cli.main([*base, "list", "--json"]) == 0
    [listed] = _json_lines(capsys.readouterr().out)
    assert [s["name"] for s in listed["scenes"]] == ["blobs", "plain"]
    assert (
        cli.main([*base, "query", "blobs", "red cube", "laptop", "--top-k", "30", "--instances", "--json"])
        == 0
    )
    got = _json_lines(capsys.readouterr().out)
    want = client.query(
        "blobs", ["red cube", "laptop"], top_k=30, fields=["similarity", "mean"], instances=True
    )
    assert [g["text"] for g in got] == ["red cube", "laptop"]
    for g, w in zip(got, want, strict=True):
        assert g["index"] == w.index.tolist() and np.allclose(g["relevancy"], w.relevancy)
        assert np.allclose(g["mean"], w.mean) and g["presence"]["found"] == w.presence.found
        assert len(g["instances"]) == len(w.instances)
        for gi, wi in zip(g["instances"], w.instances, strict=True):
            assert np.allclose(gi["obb"]["center"], wi.obb.center) and np.allclose(
                gi["aabb"]["extent"], wi.aabb.extent
            )
    assert got[0]["presence"]["found"] and not got[1]["presence"]["found"]
    png = tmp_path / "r.png"
    assert (
        cli.main([*base, "render", "blobs", "blue cone", "--size", "32x24", "--out", str(png), "--json"]) == 0
    )
    [r] = _json_lines(capsys.readouterr().out)
    assert r["files"]["relevancy"] == str(png) and (r["width"], r["height"]) == (32, 24)
    # The camera a render reports (and the viewer exports) is one `render --camera` takes back.
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(r["camera"]))
    png2 = tmp_path / "r2.png"
    assert (
        cli.main([*base, "render", "blobs", "blue cone", "--camera", str(cam), "--out", str(png2), "--json"])
        == 0
    )
    [r2] = _json_lines(capsys.readouterr().out)
    assert r2["argmax"] == r["argmax"] and png.read_bytes() == png2.read_bytes()
    cam.write_text("{}")
    assert cli.main([*base, "render", "blobs", "x", "--camera", str(cam), "--out", str(png2)]) == 1
    assert "missing viewmat" in capsys.readouterr().err
    assert cli.main([*base, "segment", "blobs", *CLASS_NAMES, "--json"]) == 0
    [seg] = _json_lines(capsys.readouterr().out)
    assert [c["name"] for c in seg["classes"]] == list(CLASS_NAMES)
    assert sum(c["gaussians"] for c in seg["classes"]) == len(seg["gaussian_index"])
    assert cli.main([*base, "health", "--json"]) == 0
    assert _json_lines(capsys.readouterr().out) == [{"service": "", "status": "SERVING"}]
    assert cli.main([*base, "info", "blobs", "--json"]) == 0
    assert _json_lines(capsys.readouterr().out)[0]["num_gaussians"] == 180
    assert cli.main([*base, "stream", "blobs", "red cube", "--frames", "4", "--size", "16x12", "--json"]) == 0
    assert _json_lines(capsys.readouterr().out)[0]["poses"] == 4


def test_every_option_says_what_it_does_and_its_default():
    ap = cli.build_parser()
    subs = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    parsers = {"fmgs-client": ap, **subs.choices}
    for name, p in parsers.items():
        for act in p._actions:
            if isinstance(act, argparse._HelpAction | argparse._SubParsersAction):
                continue
            assert act.help, f"{name} {act.dest}: no help"
            if act.option_strings and not act.required:
                assert "default" in act.help, f"{name} {act.option_strings[0]}: help does not say the default"


def test_open3d_export_of_a_real_answer(client, tmp_path):
    pytest.importorskip("open3d")
    from fmgs_client import open3d_tools as ot

    (a,) = client.query("blobs", "blue cone", top_k=60, fields=["mean"], instances=True)
    paths = ot.export_answer(a, tmp_path / "a.ply")
    assert len(paths) == 2 and all(p.stat().st_size > 0 for p in paths)
    img = decode_png(ot.screenshot(a, tmp_path / "a.png", 96, 72, method="numpy").read_bytes())
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 5


def _openssl(*args: str, cwd) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make certificates")
def test_mutual_tls(models, tmp_path):
    d = tmp_path
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "1",
             "-subj", "/CN=test-ca", "-keyout", "ca.key", "-out", "ca.pem", cwd=d)  # fmt: skip
    for name, san in (("server", "subjectAltName=IP:127.0.0.1,DNS:localhost"), ("client", None)):
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-subj",
                 f"/CN={name}", "-keyout", f"{name}.key", "-out", f"{name}.csr", cwd=d)  # fmt: skip
        ext = ["-extfile", f"{name}.ext"] if san else []
        if san:
            (d / f"{name}.ext").write_text(san + "\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                 "-CAcreateserial", "-days", "1", "-out", f"{name}.pem", *ext, cwd=d)  # fmt: skip
    srv = _start(models, tls_cert=d / "server.pem", tls_key=d / "server.key", client_ca=d / "ca.pem")
    try:
        with FmgsClient(
            srv.address, root_cert=d / "ca.pem", client_cert=d / "client.pem", client_key=d / "client.key"
        ) as c:
            assert [s.name for s in c.list_scenes()] == ["blobs", "plain"]
        with FmgsClient(srv.address, root_cert=(d / "ca.pem").read_bytes(), timeout=5) as c:
            with pytest.raises(FmgsError) as e:  # no client certificate: the handshake fails
                c.list_scenes()
            assert e.value.code == "UNAVAILABLE"
        with FmgsClient(srv.address, timeout=5) as c, pytest.raises(FmgsError):
            c.list_scenes()  # plaintext to a TLS port
        base = ["--address", srv.address, "--root-cert", str(d / "ca.pem")]
        tls = [*base, "--client-cert", str(d / "client.pem"), "--client-key", str(d / "client.key")]
        assert cli.main([*tls, "health"]) == 0
    finally:
        srv.stop(0)
