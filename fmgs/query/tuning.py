"""Speed knobs of a text query, in one place. Answers are exact whatever their values (fmgs.query.certify):
they only move work between the passes of fmgs.query.plan. Each line's comment names the report whose
figures chose it (1M field-like Gaussians, one thread), or says it bounds memory and was not timed.

Code reads them as ``tuning.NAME`` when it runs, so a test may set one with monkeypatch.
"""

from __future__ import annotations

RESCORE_CHUNK = 8192  # a memory bound, not timed
"""Rows rescored at once: bounds a rescoring pass's working memory (RESCORE_CHUNK x D x 12 bytes)."""
REFINE_ABOVE = 2048  # benchmarks/results/TUNING.md
"""More rows left than this go through tier 2 and float32 first; caps the first rescoring at k + this."""
REFINE_CHUNK = 262144  # a memory bound, not timed
"""Rows per narrowing or refinement pass: bounds its working memory (about 40 bytes per row and text)."""
TIER2_FIRST_FRACTION = 0.35  # benchmarks/results/TUNING.md
"""A text whose first tier is estimated to leave more than this share of rows starts with the second."""
HEAD_FRACTION = 0.1  # benchmarks/results/TUNING.md
"""Of those, one whose first tier + head pass is estimated to leave at most this share takes that pass."""
HEAD_TEXTS = 2  # benchmarks/results/TUNING.md
"""The head pass is taken only when at most this many texts of a request leave the first tier."""
TIER2_FIRST_STEP = 256  # benchmarks/results/TUNING.md (with HINT_BELOW)
"""Every this-many-th row makes the sample that estimates each text's first pass and hint."""
TIER2_FIRST_MIN_SAMPLE = 256  # not timed: the first tier is cheap on small scenes
"""Scenes whose sample would be smaller (under 64K rows) skip the estimate."""
HINT_BELOW = 2  # benchmarks/results/TUNING.md
"""A text's hint for certify_start is at most its sample's (HINT_BELOW ks + 1)-th best lower bound."""
TOP_SAMPLE_STEP = 64  # not timed
"""certify.top_rows estimates its cut on every this-many-th value."""
SELECT_ROOM = 1 << 18  # a memory bound, not timed
"""Rows certify.rows_at_least's kernel writes at most (a 2 MB buffer); selections keeping more use numpy."""
TIER2_HEAD = 128  # benchmarks/results/TUNING.md
"""Basis vectors of the second tier's head: what a CLIP-like or absent text's first pass reads of it."""
TIER2_TAIL_MIN = 32  # not timed
"""The second tier is split into head and tail only when the tail would hold at least this many vectors."""
