"""No import circles among the project's modules: the graph of every module under fmgs, fmgs_server,
fmgs_client and fmgs_wire, read with ``ast``, has no cycle.

An edge is any import of a project module, wherever it stands: at module level, inside a function, under
``if TYPE_CHECKING``. ``from pkg import name`` points at ``pkg.name`` when that is a module, else at
``pkg``; relative imports resolve against the importing module's package; a package ``__init__``'s lazy
export map (a dict whose values are module paths, ``fmgs.lazy``) points at each module it names. Importing
``a.b.c`` also runs ``a`` and ``a.b``, but those are not edges: a package ``__init__`` imports nothing of
its own until a lazy export is used.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("fmgs", "fmgs_server", "fmgs_client", "fmgs_wire")


def project_modules() -> dict[str, Path]:
    """Every module of PACKAGES by dotted name (a package by its own name), with its file."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules ``name`` (whose file is ``path``) imports."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]

    def project(target: str) -> str | None:  # the longest project module that target names
        while target and target not in modules:
            target = target.rpartition(".")[0]
        return target or None

    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(project(a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join([*base, node.module] if node.module else base)
            else:
                source = node.module or ""
            for a in node.names:
                sub = f"{source}.{a.name}"
                found.add(sub if sub in modules else project(source))
        elif is_package and isinstance(node, ast.Dict):  # a lazy export map: {"Name": "pkg.module"}
            for v in node.values:
                if isinstance(v, ast.Constant) and isinstance(v.value, str) and v.value in modules:
                    found.add(v.value)
    found.discard(None)
    found.discard(name)
    return found


def import_graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as [a, b, ..., a], or None (iterative depth-first search)."""
    colour = dict.fromkeys(graph, 0)  # 0 unseen, 1 on the stack, 2 done
    for start in sorted(graph):
        if colour[start]:
            continue
        stack = [(start, iter(sorted(graph[start])))]
        colour[start] = 1
        while stack:
            node, edges = stack[-1]
            nxt = next(edges, None)
            if nxt is None:
                colour[node] = 2
                stack.pop()
            elif colour.get(nxt, 2) == 1:
                path = [n for n, _ in stack]
                return [*path[path.index(nxt) :], nxt]
            elif colour.get(nxt) == 0:
                colour[nxt] = 1
                stack.append((nxt, iter(sorted(graph[nxt]))))
    return None


def test_the_graph_is_read():
    graph = import_graph()
    assert "fmgs.query.index" in graph and "fmgs_client.client" in graph
    assert "fmgs.query.state" in graph["fmgs.query.index"]
    assert "fmgs.query.engine" in graph["fmgs.query"]  # the lazy export map


def test_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
