"""Is the queried thing in this scene? A presence score from the scene's best Gaussians for the query.

Relevancy contrasts a query with four generic phrases, so the most similar thing in a scene often scores
above 0.5 ("laptop" finds a mug at 0.53). Presence contrasts it with named things instead: the query's
``PresenceConfig.pool`` best Gaussians (of the first ``PresenceConfig.rows`` of its ranking) are taken as
one group, and the group's mean embedding must be closer to the query than to every negative the query is
not a paraphrase of:

    margin = mean_f f.q - max_{n in N \\ S(q)} mean_f f.n    (f over the pool best),
    presence = sigmoid(t * margin),

where N is the scene's negatives (``VOCABULARY``, a broad list of everyday things, plus the scene's own
label names when it was built from label targets) embedded by the scene's text encoder, and S(q) the
``exclude`` negatives nearest to q by text similarity: a query may mean the same as its nearest names
("coffee cup" and "mug"), so those cannot speak against it. The query is found when presence > 0.5. A
mug's Gaussians are closer on average to "mug" than to "laptop", so "laptop" is not found there.

Why a group, and why this one: a distilled field's embeddings are noisy, and the best of 64 noisy
margins is biased upwards, so one Gaussian of a blurred mix finds absent things; mask-based
open-vocabulary methods classify a segment by its mean feature. The group is an instance's worth
(``InstanceConfig.min_points``, the fewest Gaussians the server calls an object), not all the rows: a
small object's best rows run on into its neighbours, whose mean is neither. ``rule`` "each" is the rule
before it: each row's own margin f.q - max_n f.n, the ``quorum``-th best deciding (quorum 1: the best).

A query that names a colour (fmgs.query.colours) asks the colour question on its own too: its text is
first put in canonical form (colour synonyms mapped to the plain word: "scarlet cube" -> "red cube"),
which is the q above, and the same query in every other colour joins N as contrasts that can never be
excluded as paraphrases. A red cube's Gaussians are closer to "red cube" than to "green cube", so "green
cube" is not found there, though the text encoder puts the two at 0.79. Contrasts need the query's text
(``probes``); a query given only as an embedding is decided without them.

Calibration is per scene through N: the scene's own names take part. What it cannot do: tell apart
queries the text encoder itself barely separates in anything but colour (a "purple cube" where the
scene has a "purple donut" and no cube is found when "purple donut" is among the query's nearest names);
on label-target scenes open vocabulary means text similarity of the label names, nothing more.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from fmgs.query.colours import colour_probe
from fmgs.query.vocabulary import VOCABULARY

__all__ = [
    "RULES",
    "VOCABULARY",
    "Presence",
    "PresenceConfig",
    "Probe",
    "negative_names",
    "presence",
    "presence_reference",
    "probes",
]


RULES = ("mean", "each")
"""How the best rows decide presence (``PresenceConfig.rule``)."""


@dataclass(frozen=True)
class PresenceConfig:
    """How presence is decided."""

    rows: int = 64
    """Best Gaussians of the query's ranking that are contrasted (more: slower, likelier found)."""
    exclude: int = 8
    """Negatives nearest to the query (text similarity) that are taken as possible paraphrases."""
    temperature: float = 10.0
    """Sharpness of the score (the relevancy's); the found/not-found decision does not depend on it."""
    rule: str = "mean"
    """How the best rows decide: "mean", the margin of the mean embedding of the ``pool`` best (one margin
    for the group); "each", each row's own margin, the ``quorum``-th best deciding."""
    pool: int = 10
    """With rule "mean": best Gaussians whose mean embedding decides (capped at the rows there are); an
    instance's worth (``InstanceConfig.min_points``)."""
    quorum: int = 1
    """With rule "each": best Gaussians that must each beat every negative (capped at the rows there are).
    1 lets one Gaussian decide (CLIP_PATH.md measures the rules)."""

    def __post_init__(self) -> None:
        if self.rows < 1 or self.exclude < 0 or not self.temperature > 0 or self.quorum < 1 or self.pool < 1:
            raise ValueError(
                "presence: rows >= 1, exclude >= 0, temperature > 0, pool >= 1 and quorum >= 1 required, "
                f"got {self}"
            )
        if self.pool > self.rows:
            raise ValueError(f"presence: pool must not exceed rows (the rows ranked), got {self}")
        if self.rule not in RULES:
            raise ValueError(f"presence: rule must be one of {RULES}, got {self.rule!r}")
        if self.quorum != 1 and self.rule != "each":
            raise ValueError(f"presence: a quorum needs rule 'each' (the mean has one margin), got {self}")


class Presence(NamedTuple):
    """The presence of one query."""

    score: float
    """In [0,1]: sigmoid(temperature * margin)."""
    found: bool
    """margin > 0: the pool best Gaussians' mean embedding is closer to the query than to any negative it does
    not mean (rule "each": quorum best Gaussians each are)."""
    margin: float
    """mean f.q - max mean f.n over the pool best Gaussians (float64; rule "each": the quorum-th best
    f.q - max f.n)."""
    rival: int
    """Index into the negatives, then the query's contrasts (V + s), of the one that decided the margin
    (at the mean; rule "each": at the Gaussian whose margin it is)."""


class Probe(NamedTuple):
    """What one query's presence is decided with."""

    query: torch.Tensor
    """[D] the canonical query's embedding (the query's own when it names no colour)."""
    contrasts: torch.Tensor
    """[S,D] embeddings of its colour contrasts (S = 0 when it names no colour)."""
    names: tuple[str, ...]
    """[S] the contrasts' texts (to name a rival)."""


def probes(
    texts: Sequence[str], queries: torch.Tensor, encode: Callable[[list[str]], torch.Tensor]
) -> list[Probe]:
    """The presence probe of each text; queries [n,D] are the texts' embeddings (used as they are for
    texts that name no colour), ``encode(list of texts) -> [m,D]`` the scene's text encoder. Every
    canonical form and contrast of the request is encoded in one call."""
    colour = [colour_probe(t) for t in texts]
    extra = [t for c in colour if c.contrasts for t in (c.canonical, *c.contrasts)]
    vecs = encode(extra).float() if extra else None
    out, at = [], 0
    for j, c in enumerate(colour):
        if not c.contrasts:
            out.append(Probe(queries[j], queries.new_zeros((0, queries.shape[1])), ()))
            continue
        n = 1 + len(c.contrasts)
        out.append(Probe(vecs[at], vecs[at + 1 : at + n], c.contrasts))
        at += n
    return out


def negative_names(label_names: tuple[str, ...] | list[str] = ()) -> list[str]:
    """``VOCABULARY`` plus the scene's label names not already in it (order kept, case-insensitive)."""
    seen = {v.lower() for v in VOCABULARY}
    out = list(VOCABULARY)
    for n in label_names:
        if n.strip() and n.lower() not in seen:
            seen.add(n.lower())
            out.append(n)
    return out


def presence(
    fq: torch.Tensor,
    fn: torch.Tensor,
    qn: torch.Tensor,
    cfg: PresenceConfig = PresenceConfig(),
    fc: torch.Tensor | None = None,
) -> Presence:
    """Presence from dots, computed in float64: f.q [T] and f.n [T,V] of the query's best Gaussians
    (T >= 1), the query's text similarity to each negative q.n [V] (V > cfg.exclude), and f.c [T,S] of
    the best Gaussians with the query's colour contrasts (never excluded; None or S = 0: none)."""
    fq, fn, qn = fq.double().reshape(-1), fn.double(), qn.double().reshape(-1)
    T, V = fn.shape if fn.ndim == 2 else (-1, -1)
    if T < 1 or len(fq) != T or len(qn) != V or V <= cfg.exclude:
        raise ValueError(
            f"presence needs f.q [T>=1], f.n [T,V] and q.n [V] with V > {cfg.exclude}; got "
            f"{list(fq.shape)}, {list(fn.shape)}, {list(qn.shape)}"
        )
    keep = torch.ones(V, dtype=torch.bool)
    if cfg.exclude:
        keep[torch.topk(qn, cfg.exclude).indices] = False
    kept = torch.nonzero(keep).reshape(-1)
    if fc is not None and fc.shape[-1]:
        if fc.shape != (T, fc.shape[-1]):
            raise ValueError(f"presence: contrast dots must be [{T},S], got {list(fc.shape)}")
        fn = torch.cat([fn, fc.double()], 1)
        kept = torch.cat([kept, torch.arange(V, V + fc.shape[1])])
    if cfg.rule == "mean":  # the mean embedding's dots are the dots' means
        p = min(cfg.pool, T)
        rival_dot, rival = fn[:p, kept].mean(0).max(0)
        m = float(fq[:p].mean() - rival_dot)
        return Presence(_sigmoid(cfg.temperature * m), m > 0, m, int(kept[rival]))
    rival_dot, rival = fn[:, kept].max(1)
    margins = fq - rival_dot
    # The quorum-th best margin; a stable sort keeps the first row among equal margins.
    b = int(torch.sort(margins, descending=True, stable=True).indices[min(cfg.quorum, T) - 1])
    m = float(margins[b])
    return Presence(_sigmoid(cfg.temperature * m), m > 0, m, int(kept[rival[b]]))


def _sigmoid(x: float) -> float:
    return float(torch.sigmoid(torch.tensor(x, dtype=torch.float64)))


def presence_reference(
    query: torch.Tensor,
    best: torch.Tensor,
    negatives: torch.Tensor,
    cfg: PresenceConfig = PresenceConfig(),
    contrasts: torch.Tensor | None = None,
) -> Presence:
    """Twin of ``presence`` from the vectors: unit query [D], best Gaussians' embeddings [T,D] (best
    first), unit negatives [V,D] and unit contrasts [S,D], one Gaussian and one negative at a time
    (sorting for the exclusion); with rule "mean", the pool first rows' mean vector is the one Gaussian."""
    q = [float(x) for x in query.double().reshape(-1)]
    dot = lambda a, b: sum(x * y for x, y in zip(a, b, strict=True))  # noqa: E731
    negs = [[float(x) for x in row] for row in negatives.double()]
    order = sorted(range(len(negs)), key=lambda i: (-dot(negs[i], q), i))
    excluded = set(order[: cfg.exclude])
    if contrasts is not None:
        negs += [[float(x) for x in row] for row in contrasts.double()]
    rows = best.double()
    if cfg.rule == "mean":
        rows = rows[: cfg.pool].mean(0, keepdim=True)
    per_row = []
    for t, row in enumerate(rows):
        f = [float(x) for x in row]
        r = max((i for i in range(len(negs)) if i not in excluded), key=lambda i: (dot(f, negs[i]), -i))
        per_row.append((dot(f, q) - dot(f, negs[r]), t, r))
    ordered = sorted(per_row, key=lambda x: (-x[0], x[1]))
    m, _, r = ordered[min(cfg.quorum, len(ordered)) - 1]
    return Presence(_sigmoid(cfg.temperature * m), m > 0, m, r)
