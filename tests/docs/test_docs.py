"""The documentation holds together: every relative link of README.md, CONTRIBUTING.md and docs/**/*.md
reaches a file (and a ``#anchor`` a heading of it), and every command line the docs show (``fmgs SUB``,
``fmgs-server``, ``fmgs-client SUB`` in code spans and shell blocks) answers ``--help`` and knows every
``--flag`` shown with it.

``--help`` runs in this process through each command's argparse parser (``build_parser``), once per
distinct command, so the test costs a fraction of a second beyond the imports.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from functools import cache
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", *(ROOT / "docs").rglob("*.md")])
SHELL_BLOCKS = ("", "bash", "sh", "shell", "console")
"""Fenced blocks whose lines are read as command lines (others: python, toml, text, ...)."""
COMMANDS = ("fmgs", "fmgs-server", "fmgs-client")


# ---------------------------------------------------------------- markdown


class Page(NamedTuple):
    prose: list[str]
    """Lines outside fenced blocks (links live here)."""
    blocks: list[tuple[str, list[str]]]
    """Fenced blocks: (info string, lines)."""


def read_page(path: Path) -> Page:
    prose, blocks, fence, info, body = [], [], None, "", []
    for line in path.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^\s*(`{3,}|~{3,})\s*([\w+-]*)", line)
        if fence is None and m:
            fence, info, body = m.group(1), m.group(2).lower(), []
        elif fence is not None and line.strip().startswith(fence):
            blocks.append((info, body))
            fence = None
        elif fence is not None:
            body.append(line)
        else:
            prose.append(line)
    return Page(prose, blocks)


def code_spans(line: str) -> list[str]:
    return [m.group(2) for m in re.finditer(r"(`+)(.+?)\1", line)]


def without_code(line: str) -> str:
    return re.sub(r"(`+)(.+?)\1", "", line)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: rendered text, lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links and images: their text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "")
    text = re.sub(r"\*{1,3}(\S.*?)\*{1,3}", r"\1", text)  # emphasis; intraword _ is not
    text = re.sub(r"(?<!\w)_{1,3}(\S.*?)_{1,3}(?!\w)", r"\1", text)
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in read_page(path).prose:
        m = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
        if m:
            base = slug(m.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
        out.update(re.findall(r"<a\s+(?:name|id)=\"([^\"]+)\"", line))
    return frozenset(out)


def links(path: Path) -> list[str]:
    found = []
    for line in read_page(path).prose:
        text = without_code(line)
        found += re.findall(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)
        m = re.match(r"^\s*\[[^\]]+\]:\s*(\S+)", text)
        if m:
            found.append(m.group(1))
    return found


def broken_link(page: Path, target: str) -> str | None:
    """Why ``target`` (a link on ``page``) does not resolve, or None."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
        return None
    file, _, anchor = target.partition("#")
    dest = (page.parent / file).resolve() if file else page
    if not dest.exists():
        return f"{file}: no such file"
    if ROOT not in dest.parents and dest != ROOT:
        return f"{file}: outside the repository"
    if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
        return f"#{anchor}: no such heading in {dest.relative_to(ROOT)}"
    return None


def all_links() -> list[tuple[str, str]]:
    return [(str(p.relative_to(ROOT)), t) for p in PAGES for t in links(p)]


# ---------------------------------------------------------------- commands


class Shown(NamedTuple):
    command: tuple[str, ...]
    """The command and its subcommand: ("fmgs", "build"), ("fmgs-server",), ..."""
    flags: tuple[str, ...]
    """The --flags shown with it."""


def parse_command(line: str) -> Shown | None:
    """The command a shell line or code span runs, when it is one of ours."""
    try:
        words = shlex.split(line, comments=True)
    except ValueError:  # an unbalanced quote in prose: read it word by word
        words = line.split()
    while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):  # VAR=value prefixes
        words = words[1:]
    if not words or Path(words[0]).name not in COMMANDS:
        return None
    name, rest = Path(words[0]).name, words[1:]
    flags = tuple(w.split("=", 1)[0] for w in rest if re.match(r"^--[a-z0-9][a-z0-9-]*(=|$)", w))
    if name == "fmgs-server":
        return Shown((name,), flags)
    i = 0
    while name == "fmgs-client" and i < len(rest) and rest[i].startswith("--"):
        i += 1 if "=" in rest[i] else 2  # the client's global options all take a value
    sub = rest[i] if i < len(rest) else ""
    if not re.fullmatch(r"[a-z][a-z0-9-]*", sub):  # none, or a placeholder such as SUB
        return Shown((name,), ())
    return Shown((name, sub), flags)


def shell_lines(lines: list[str]) -> list[str]:
    """Logical command lines of a shell block: continuations joined, split at && ; | and $( )."""
    joined, out = " ".join(ln.rstrip()[:-1] if ln.rstrip().endswith("\\") else ln + "\n" for ln in lines), []
    for ln in joined.splitlines():
        ln = re.sub(r"(^|\s)#.*$", "", ln.strip().removeprefix("$ "))
        out += [" ".join(p.split()) for p in re.split(r"&&|\|\||;|\||\$\(|\)", ln) if p.strip()]
    return out


def shown_commands() -> dict[Shown, list[str]]:
    """Every command the docs show, with where."""
    found: dict[Shown, list[str]] = {}
    for page in PAGES:
        doc = read_page(page)
        candidates = [span for line in doc.prose for span in code_spans(line)]
        for info, body in doc.blocks:
            if info in SHELL_BLOCKS:
                candidates += shell_lines(body)
        for text in candidates:
            shown = parse_command(text)
            if shown is not None:
                found.setdefault(shown, []).append(f"{page.relative_to(ROOT)}: {text}")
    return found


def parser_of(command: tuple[str, ...]):
    """The argparse parser and the argv prefix that reaches ``command``'s own parser."""
    name, sub = command[0], command[1:]
    if name == "fmgs-server" or command == ("fmgs", "serve"):  # fmgs serve execs fmgs-server
        from fmgs_server.cli import build_parser

        return build_parser(" ".join(command)), []
    if name == "fmgs":
        from fmgs.cli import build_parser

        return build_parser(), list(sub)
    from fmgs_client.cli import build_parser

    return build_parser(), list(sub)


@cache
def help_text(command: tuple[str, ...]) -> tuple[int, str]:
    """(exit status, output) of ``command --help``, run through the command's parser in this process."""
    parser, argv = parser_of(command)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            parser.parse_args([*argv, "--help"])
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 1
    return code, out.getvalue() + err.getvalue()


# ---------------------------------------------------------------- tests


def test_pages_exist():
    names = {str(p.relative_to(ROOT)) for p in PAGES}
    assert {"README.md", "CONTRIBUTING.md", "docs/architecture.md"} <= names


@pytest.mark.parametrize(("page", "target"), all_links())
def test_relative_link_resolves(page, target):
    why = broken_link(ROOT / page, target)
    assert why is None, f"{page}: link {target}: {why}"


def test_commands_answer_help_and_know_their_flags():
    shown = shown_commands()
    commands = {s.command for s in shown}
    assert {("fmgs", "build"), ("fmgs-server",), ("fmgs-client", "query")} <= commands, commands
    problems = []
    for s, where in sorted(shown.items()):
        code, text = help_text(s.command)
        text += help_text(s.command[:1])[1]  # options before the subcommand (fmgs-client --address)
        if code != 0:
            problems.append(f"`{' '.join(s.command)} --help` exited {code} (shown in {where[0]})")
            continue
        unknown = [f for f in s.flags if not re.search(rf"(?<![\w-]){re.escape(f)}(?![\w-])", text)]
        if unknown:
            problems.append(f"{' '.join(s.command)} has no {', '.join(unknown)} (shown in {where[0]})")
    assert not problems, "\n".join(problems)


def test_slugs_follow_github():
    assert slug("Limits (`fmgs_server.config.ServerConfig`, defaults)") == (
        "limits-fmgs_serverconfigserverconfig-defaults"
    )
    assert slug('Presence: "not here"') == "presence-not-here"
    assert slug("The [wire](x.md) *contract*") == "the-wire-contract"
    assert slug("`max_top_k` and _emphasis_") == "max_top_k-and-emphasis"


def test_command_lines_are_parsed():
    assert parse_command("fmgs build DATA --name kitchen --gs-steps=7000") == Shown(
        ("fmgs", "build"), ("--name", "--gs-steps")
    )
    assert parse_command(
        ".venv/bin/fmgs-client --address H:1 --token-file t query demo x --top-k 5"
    ) == Shown(("fmgs-client", "query"), ("--address", "--token-file", "--top-k"))
    assert parse_command("FMGS_CLIENT=x fmgs-server --ray auto") == Shown(("fmgs-server",), ("--ray",))
    assert parse_command("fmgs-client SUB --help") == Shown(("fmgs-client",), ())
    assert parse_command("from fmgs import Camera") is None
    assert shell_lines(["a && fmgs info x.ply \\", "  --help  # comment", "echo $(fmgs-client list)"]) == [
        "a",
        "fmgs info x.ply --help",
        "echo",
        "fmgs-client list",
    ]
