"""The stored embeddings' neighbour mean (fmgs.field.neighbours) against its brute-force twin."""

from __future__ import annotations

import pytest
import torch

from fmgs.field import neighbours as nbm
from fmgs.field.neighbours import REACH_SIGMAS, neighbour_mean, neighbour_mean_reference, reach_of
from fmgs.vecmath import safe_normalize


def _scene(n: int, d: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    # Clustered means with a wide spread of densities (float64: distinct distances, no ties).
    centres = torch.randn(5, 3, generator=g, dtype=torch.float64) * 3
    pts = centres[torch.randint(0, 5, (n,), generator=g)] + torch.randn(
        n, 3, generator=g, dtype=torch.float64
    ) * (10 ** torch.empty(n, 1, dtype=torch.float64).uniform_(-3, 0, generator=g))
    # Reaches from a tenth to ten times the typical spacing: some Gaussians reach none of their k
    # nearest, some all of them.
    reach = 10 ** torch.empty(n, dtype=torch.float64).uniform_(-4, 0, generator=g)
    return pts, reach, safe_normalize(torch.randn(n, d, generator=g))


@pytest.mark.parametrize("k", [1, 2, 8, 31])
def test_matches_brute_force(k, monkeypatch):
    monkeypatch.setattr(nbm, "QUERY_BLOCK", 97)  # several blocks, the last one partial
    pts, reach, emb = _scene(1000, 16, k)
    out = neighbour_mean(pts, reach, emb, k)
    ref = neighbour_mean_reference(pts, reach, emb, k)
    if k > 1:  # the reaches matter: some Gaussians kept all k, some none beside themselves
        far = neighbour_mean_reference(pts, torch.full_like(reach, 1e9), emb, k)
        alone = (out - emb).abs().amax(1) < 1e-6  # a neighbour out of reach: kept as it was
        assert 0 < int(alone.sum()) < len(out) and not torch.allclose(out, far)
    assert out.dtype == torch.float32 and out.shape == emb.shape
    torch.testing.assert_close(out, ref, rtol=0, atol=2e-6)
    assert torch.allclose(out.norm(dim=1), torch.ones(len(out)), atol=1e-5)


def test_k1_is_the_field_itself_and_k_is_capped():
    pts, _, emb = _scene(50, 8, 3)
    big = torch.full((50,), 1e9, dtype=torch.float64)
    assert torch.equal(neighbour_mean(pts, big, emb, 1), emb)
    everyone = neighbour_mean(pts, big, emb, 1000)  # k > M: every Gaussian averages all of them
    mean = safe_normalize(emb.sum(0, keepdim=True)).expand_as(emb)
    torch.testing.assert_close(everyone, mean, rtol=0, atol=2e-6)
    assert neighbour_mean(pts[:0], big[:0], emb[:0], 8).shape == (0, 8)


def test_a_gaussian_at_the_rim_is_lowered_and_one_in_the_midst_is_kept():
    # A line of "object" Gaussians (embedding a) beside a line of "floor" ones (embedding b): after
    # the mean, the object's best Gaussian (highest dot with a) lies away from the floor.
    a, b = torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0])
    x = torch.arange(20, dtype=torch.float64)
    pts = torch.stack([x, torch.zeros(20, dtype=torch.float64), torch.zeros(20, dtype=torch.float64)], 1)
    emb = torch.stack([a if i < 10 else b for i in range(20)])
    out = neighbour_mean(pts, torch.full((20,), 5.0, dtype=torch.float64), emb, 4)
    dots = out @ a
    assert float(dots[:7].min()) == pytest.approx(1.0)  # the object's midst is untouched
    assert float(dots[9]) < float(dots[5])  # its rim, beside the floor, is lowered


def test_cancelling_neighbours_give_zero_not_nan():
    pts = torch.tensor([[0.0, 0, 0], [1e-9, 0, 0]], dtype=torch.float64)
    emb = torch.tensor([[1.0, 0], [-1.0, 0]])
    out = neighbour_mean(pts, torch.ones(2, dtype=torch.float64), emb, 2)
    assert torch.isfinite(out).all() and torch.equal(out, torch.zeros(2, 2))


def test_bad_k_is_refused():
    pts, reach, emb = _scene(10, 4, 0)
    with pytest.raises(ValueError, match="neighbours"):
        neighbour_mean(pts, reach, emb, 0)


def test_reach_is_twice_the_largest_scale():
    scales = torch.tensor([[0.1, 0.3, 0.2], [1e-6, 1e-7, 1e-8]])
    assert REACH_SIGMAS == 2.0
    torch.testing.assert_close(reach_of(scales), torch.tensor([0.6, 2e-6], dtype=torch.float64))


def test_a_gaussian_with_a_neighbour_out_of_reach_keeps_its_own():
    # Two "object" Gaussians beside each other and a floor one 1 unit away, k=3: with a reach of 0.5
    # no Gaussian has both its nearest within reach, so none is averaged (the floor stays out of the
    # object, and the object's pair is not averaged either); a reach of 2 averages all three.
    pts = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [1.1, 0, 0]], dtype=torch.float64)
    emb = torch.tensor([[1.0, 0], [1.0, 0], [0.0, 1]])
    near = neighbour_mean(pts, torch.full((3,), 0.5, dtype=torch.float64), emb, 3)
    far = neighbour_mean(pts, torch.full((3,), 2.0, dtype=torch.float64), emb, 3)
    assert torch.equal(near, emb)
    assert float(far[1, 1]) > 0.3 and float(far[2, 0]) > 0.3


def test_only_dense_neighbourhoods_are_averaged():
    # A dense cluster of 10 "object" Gaussians (spacing about 0.01, reach 0.1) touching one "floor"
    # Gaussian, and a sparse pair (spacing 1, reach 2) beside a third Gaussian 10 units away. k=4:
    # every cluster Gaussian has its 3 nearest within reach and is averaged; in the sparse group
    # each Gaussian has at most one neighbour within reach and keeps its own embedding.
    a, b = torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0])
    line = (torch.arange(11, dtype=torch.float64) * 0.01) ** 1.1  # uneven spacing: no ties in distance
    cluster = torch.stack(
        [line, torch.zeros(11, dtype=torch.float64), torch.zeros(11, dtype=torch.float64)], 1
    )
    sparse = torch.tensor([[100.0, 0, 0], [101.0, 0, 0], [111.0, 0, 0]], dtype=torch.float64)
    pts = torch.cat([cluster, sparse])
    emb = torch.stack([a] * 10 + [b] + [a, b, b])
    reach = torch.tensor([0.1] * 11 + [2.0] * 3, dtype=torch.float64)
    out = neighbour_mean(pts, reach, emb, 4)
    assert not torch.equal(out[10], emb[10]) and float(out[10] @ a) > 0.5  # the floor one, averaged
    assert float(out[0] @ a) == pytest.approx(1.0)  # the cluster's far end: all its neighbours are a
    assert torch.equal(out[11:], emb[11:])  # the sparse ones: not mixed with their one neighbour
    torch.testing.assert_close(out, neighbour_mean_reference(pts, reach, emb, 4), rtol=0, atol=2e-6)
