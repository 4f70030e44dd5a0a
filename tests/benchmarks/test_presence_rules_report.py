"""The committed presence-rules report (benchmarks/results/PRESENCE_RULES.md, the dev scenes the served
presence rule was chosen on) is written from its figures, and the served rule is the best there on the
CLIP path among the rules it measures."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.presence_rules import RULES, report
from fmgs.query.presence import PresenceConfig

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def _presence(d: dict, variant: str, rule: str) -> float:
    f, p, a, n = (sum(x) for x in zip(*(s[variant][rule]["counts"] for s in d["scenes"]), strict=True))
    return (f + a) / (p + n)


def test_committed_report_is_written_from_its_figures():
    d = json.loads((RESULTS / "PRESENCE_RULES.json").read_text())
    assert report(d) == (RESULTS / "PRESENCE_RULES.md").read_text()


def test_the_served_rule_is_the_best_on_the_clip_path_there():
    d = json.loads((RESULTS / "PRESENCE_RULES.json").read_text())
    served = [name for name, cfg in RULES.items() if cfg == PresenceConfig()]
    assert served == ["mean of 10"]
    clip = [v for v in d["variants"] if v != "labels"]
    assert clip and "labels" in d["variants"]
    for v in clip:
        best = max(_presence(d, v, r) for r in RULES)
        assert _presence(d, v, served[0]) == best, v
        assert best > _presence(d, v, "best (each, quorum 1)"), v  # the rule before it is not


def test_presence_docs_quote_the_dev_figures():
    d = json.loads((RESULTS / "PRESENCE_RULES.json").read_text())
    docs = (RESULTS.parents[1] / "docs" / "presence.md").read_text()
    first = {**d, "scenes": d["scenes"][:1]}  # the rule was picked on the first seed alone
    for fig in (d, first):
        for r in ("best (each, quorum 1)", "quorum 10 (each)", "mean of 10"):
            assert f"{_presence(fig, 'dominant', r):.3f}" in docs, r
    for r in ("best (each, quorum 1)", "mean of 10"):
        assert f"{_presence(d, 'labels', r):.3f}" in docs, r
    assert _presence(d, "labels", "mean of 10") == max(_presence(d, "labels", r) for r in RULES)
    seeds = d["seeds"]
    assert (f"seed {seeds[0]}," if len(seeds) == 1 else "seeds " + " and ".join(map(str, seeds))) in docs
    assert f"picked on seed {seeds[0]} alone" in docs
