"""Figures in the docs come from the reports they cite: in every paragraph, list item or table row of
README.md and docs/**/*.md that links to a report under ``benchmarks/results/``, each number of the prose
(outside code spans and link targets) must be a number of one of the cited reports (its ``.md`` or its
``.json``), as written or rounded to the digits the page shows. A number that is a setting, not a
measurement, is listed in ``SETTINGS`` with the reason.

This is what catches a page that still quotes an old run after the report was re-measured. A figure in a
block that cites no report is not checked here; CONTRIBUTING asks for the citation.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import pytest

from tests.docs.test_docs import read_page

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
RESULTS = ROOT / "benchmarks" / "results"

NUMBER = re.compile(r"(?<![\w.\-/#^])(\d[\d,]*(?:\.\d+)?)(?![\w]|\.\d)(\s?%)?")
"""A number standing alone: not part of a name (p90, x86_64, H200, 2^20), a path or a version (4.2.1);
the second group marks a percentage."""
REPORT_LINK = re.compile(r"\]\(([^)]*?benchmarks/results/[A-Za-z0-9_]+\.(?:md|json))(?:#[^)]*)?\)")

SETTINGS: dict[str, dict[str, str]] = {
    "README.md": {"50051": "the server's default port"},
    "docs/build.md": {
        "90": "--background-transmittance 0.9, a setting",
        "40": "make_demo.py's run time as its docstring states it (DEMO.md records the build)",
    },
    "docs/field.md": {
        "0.25": "the paper's opacity threshold",
        "2": "the paper's projected-radius threshold (px)",
    },
}
"""{page: {number as written: why it is not a measured figure}}."""


def blocks(path: Path) -> list[str]:
    """The page's prose split into paragraphs, list items, headings and table rows (fenced code left
    out), each joined into one line."""
    out: list[str] = []
    cur: list[str] = []
    for line in read_page(path).prose:
        starts = re.match(r"\s*([-*+]|\d+\.)\s", line) or line.lstrip().startswith(("|", "#"))
        if not line.strip() or starts:
            if cur:
                out.append(" ".join(cur))
            cur = [line.strip()] if line.strip() else []
            if line.lstrip().startswith(("|", "#")):
                out.append(line.strip())
                cur = []
        else:
            cur.append(line.strip())
    if cur:
        out.append(" ".join(cur))
    return out


def numbers(text: str) -> list[str]:
    """The numbers of a block's prose (code spans, link targets and HTML comments removed); a percentage
    keeps its sign ("99.3%")."""
    text = re.sub(r"<!--.*?-->", "", text)
    text = re.sub(r"(`+)(.+?)\1", "", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    return [n + ("%" if pct else "") for n, pct in NUMBER.findall(text)]


@cache
def report_numbers(report: Path) -> tuple[float, ...]:
    """Every number in a report's markdown and its JSON twin."""
    text = ""
    for f in (report.with_suffix(".md"), report.with_suffix(".json")):
        if f.is_file():
            text += f.read_text(encoding="utf-8") + "\n"
    found = re.findall(r"-?\d[\d,]*(?:\.\d+)?(?:[eE][-+]?\d+)?", text)
    return tuple(sorted({float(n.replace(",", "")) for n in found}))


def quoted_by(figure: str, values: tuple[float, ...]) -> bool:
    """Whether ``figure`` (as written on the page) is one of ``values`` rounded to its digits; a
    percentage may also be a fraction of the report's (99.3% of 0.993)."""
    pct = figure.endswith("%")
    text = figure.rstrip("%").replace(",", "")
    v = float(text)
    digits = len(text.split(".")[1]) if "." in text else 0
    half = 0.5 * 10.0**-digits + 1e-9 * max(1.0, abs(v))
    scales = (1.0, 100.0) if pct else (1.0,)
    return any(abs(k * x - v) <= half for x in values for k in scales)


def cited_figures() -> list[tuple[str, str, str, tuple[Path, ...]]]:
    """(page, block, number, cited reports) for every number in a block that cites a report."""
    out = []
    for page in PAGES:
        rel = page.relative_to(ROOT).as_posix()
        for block in blocks(page):
            reports = tuple(
                dict.fromkeys((page.parent / link).resolve() for link in REPORT_LINK.findall(block))
            )
            if not reports:
                continue
            for n in numbers(block):
                out.append((rel, block, n, reports))
    return out


def test_the_check_sees_the_cited_figures():
    """The scan itself: it finds figures on the pages, and every cited report exists."""
    found = cited_figures()
    assert len(found) > 150
    assert {p for p, *_ in found} >= {"README.md", "docs/engine.md", "docs/field.md", "docs/limits.md"}
    missing = sorted({r for *_, reports in found for r in reports if not r.with_suffix(".md").is_file()})
    assert not missing, missing


def test_rounding_and_percent_rules():
    values = (0.639, 31.5, 33.3, 0.993, 1547.0)
    assert quoted_by("0.639", values) and quoted_by("0.64", values) and not quoted_by("0.65", values)
    assert quoted_by("32", values) and quoted_by("33", values) and not quoted_by("35", values)
    assert quoted_by("99.3%", values) and not quoted_by("99.3", values) and not quoted_by("99.4%", values)
    assert quoted_by("1,547", values) and numbers("at 99.3 % and `0.5` [x](a/0.7.md) 4.2.1") == ["99.3%"]


@pytest.mark.parametrize("page", [p.relative_to(ROOT).as_posix() for p in PAGES])
def test_every_cited_figure_is_in_the_cited_report(page):
    allowed = SETTINGS.get(page, {})
    stale = []
    for rel, block, n, reports in cited_figures():
        if rel != page or n.rstrip("%") in allowed:
            continue
        values = tuple(v for r in reports for v in report_numbers(r))
        if not quoted_by(n, values):
            names = ", ".join(r.name for r in reports)
            stale.append(f"{n!r} is not in {names}: ...{block[:160]}...")
    assert not stale, "\n".join(stale)


def _readme() -> str:
    return " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())


def test_readme_text_query_figures_are_text_md():
    """The README's text-query ranges are TEXT.json's medians at k <= 100, rounded: queries near the scene
    (near, typical, ties) and CLIP-like and absent ones, each below faiss IVF-SQ8 on every set."""
    import json

    sets = json.loads((RESULTS / "TEXT.json").read_text())["text"]["sets"]

    def span(kinds: tuple[str, ...]) -> str:
        ms = [sets[f"{k}/k={n}"]["ours_ms_median"] for k in kinds for n in (1, 100)]
        return f"{round(min(ms))}-{round(max(ms))} ms"

    readme = _readme()
    assert f"{span(('near', 'typical', 'ties'))} for queries near the scene" in readme
    assert f"{span(('clip', 'absent'))} for CLIP-like and absent ones at k ≤ 100" in readme
    assert "below faiss IVF-SQ8 (not exact) on every query set" in readme
    assert all(s["ours_ms_median"] < s["faiss_ivf_sq8_refine_ms_median"] for s in sets.values())


def test_readme_field_figures_are_field_md_and_clip_path():
    """The README's label-target figures are FIELD.md's mean row at the default K (8) and its presence line;
    its CLIP-target figures are CLIP_PATH.json's default blend against labels."""
    import json

    from benchmarks.clip_path import summary
    from fmgs.build.config import EMBEDDING_NEIGHBOURS

    field = (RESULTS / "FIELD.md").read_text(encoding="utf-8")
    k = EMBEDDING_NEIGHBOURS
    row = re.search(rf"^\| \*\*mean\*\* \| {k} \| ([\d.]+%) \| ([\d.]+%) \| ([\d.]+) \|", field, re.M)
    assert row, f"FIELD.md has no mean row at K={k}"
    two_d, three_d, miou = row.groups()
    presence = re.search(r"Present queries found: \d+/\d+ \(([\d.]+%)\); absent queries not found: "
                         r"\d+/\d+ \(([\d.]+%)\)", field)  # fmt: skip
    assert presence
    readme = _readme()
    assert f"mIoU {miou}, 2D localisation {two_d}, 3D {three_d}" in readme
    assert f"presence {presence[1]} found / {presence[2]} not found" in readme
    rows = json.loads((RESULTS / "CLIP_PATH.json").read_text())["rows"]
    clip, labels = summary(rows, "dominant")["miou"], summary(rows, "labels")["miou"]
    assert f"mIoU {clip:.3f} against {labels:.3f}" in readme
