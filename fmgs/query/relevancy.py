"""LERF/FMGS relevancy against canonical phrases, computed stably.

r(q) = min_n exp(t f.q) / (exp(t f.q) + exp(t f.c_n)) = min_n sigmoid(t (f.q - f.c_n)),
the sigmoid form never overflows however large the logits are. It is applied to the feature as it is
(a Gaussian's unit embedding, or a rendered blend that is not renormalised, as in the reference code).
"""

from __future__ import annotations

import torch

from fmgs.scene.manifest import CANONICAL_PHRASES

__all__ = ["CANONICAL_PHRASES", "TEMPERATURE", "relevancy", "relevancy_reference"]

TEMPERATURE = 10.0


def relevancy(
    query_dots: torch.Tensor, canonical_dots: torch.Tensor, temperature: float = TEMPERATURE
) -> torch.Tensor:
    """[...] relevancy from f.q [...] and f.c_n [..., C] (float32 or float64; C >= 1)."""
    # min_n sigmoid(t(q - c_n)) = sigmoid(t(q - max_n c_n)) exactly: subtraction, scaling and sigmoid are
    # monotone in c_n, so one sigmoid per element replaces C of them.
    return torch.sigmoid(temperature * (query_dots.to(canonical_dots.dtype) - canonical_dots.amax(-1)))


def relevancy_reference(
    query_dots: torch.Tensor, canonical_dots: torch.Tensor, temperature: float = TEMPERATURE
) -> torch.Tensor:
    """Twin of ``relevancy`` in the paper's literal form, evaluated in float64 with the log-sum-exp shift."""
    q = query_dots.to(torch.float64)[..., None]
    c = canonical_dots.to(torch.float64)
    m = torch.maximum(q, c) * temperature
    a, b = torch.exp(temperature * q - m), torch.exp(temperature * c - m)
    return (a / (a + b)).amin(-1)
