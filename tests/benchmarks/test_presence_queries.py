"""The presence catalogue of a world scene (benchmarks.unseen.world_presence_queries): every kind is asked,
and nothing asked as absent names a placed object."""

from __future__ import annotations

import numpy as np

from benchmarks.unseen import UNRELATED, presence_queries
from fmgs.synthworld import SHAPES, sample_objects, world_object


def test_world_catalogue_asks_each_kind_and_no_absent_text_is_placed():
    objs = sample_objects(np.random.default_rng(3), 10, novel=3)
    names = ["background", "floor", *(o.name for o in objs)]
    q = presence_queries(names)
    kinds = {k for k, _ in q}
    assert kinds == {"name", "paraphrase", "absent object", "colour swap", "unrelated"}
    assert [t for k, t in q if k == "name"] == names[2:]
    placed = {(o.colour, o.shape) for o in objs}
    for kind, text in q:
        if kind == "colour swap":
            o = world_object(text)
            assert (o.colour, o.shape) not in placed, text
        if kind == "absent object":
            assert text.split()[-1] in SHAPES and text.split()[-1] not in {s for _, s in placed}, text
    assert sum(k == "absent object" for k, _ in q) == len(SHAPES) - len({s for _, s in placed})
    assert [t for k, t in q if k == "unrelated"] == list(UNRELATED)
