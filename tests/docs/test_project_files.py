"""The project's own papers: LICENSE (Apache-2.0), CITATION.cff and CHANGELOG.md exist, and the citation and
the changelog name the version pyproject.toml declares."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def pyproject_version() -> str:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]


def test_license_is_apache_2():
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "END OF TERMS AND CONDITIONS" in text  # the full text, not a notice


def test_citation_names_the_version_and_the_paper():
    text = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    top = dict(re.findall(r"^([\w-]+):[ \t]*\"?([^\"\n]*)\"?[ \t]*$", text, re.MULTILINE))
    assert top.get("cff-version") == "1.2.0"
    assert top.get("type") == "software" and top.get("title") == "FMGS"
    assert top.get("version") == pyproject_version(), "CITATION.cff's version differs from pyproject's"
    assert top.get("license") == "Apache-2.0"
    assert "2401.01970" in text  # the FMGS paper, the method this software implements


def test_changelog_has_an_entry_for_the_version():
    text = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    version = pyproject_version()
    entry = re.search(rf"^##\s+\[?{re.escape(version)}\b", text, re.MULTILINE)
    assert entry, f"CHANGELOG.md has no entry for {version}"
