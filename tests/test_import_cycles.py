"""No import circle in the source tree: the graph of every ``import`` in station/, drivers/, mocks/ and procedures/
(module level, inside functions and under ``if TYPE_CHECKING:`` alike: a deferred import that closes a circle only
hides it, and an annotation that names a module's importer is the same dependency on paper) is parsed with ``ast``
and must have no cycle. A circle means two modules each need a piece of the other; that piece belongs in a third
module both import, or the lower one states what it needs as a small ``Protocol`` (docs/architecture.md, "Import
rules").

What is not an edge: an import of one's own enclosing package (Python loads every parent package before a
submodule anyway). An edge goes
to the module an import names (``from pkg import sub``: to ``pkg.sub`` when that is a module of the tree, else to
``pkg``); a package that names its submodules for lazy loading (``station.lazy.lazy_names``) does so in strings,
which are no import."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"station": "station", "drivers": "station.drivers", "mocks": "station.mocks",
           "procedures": "station.procedures"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = [FOLDERS[rel.parts[0]], *rel.parts[1:]]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    out = {}
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            out[_module_name(path)] = path
    return out


def _targets(node: ast.AST, module: str, is_package: bool, known: set[str]) -> list[str]:
    """The modules of the tree one import statement loads."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:
            base = module.split(".")
            base = base[:len(base) - node.level + (1 if is_package else 0)]
            pkg = ".".join([*base, node.module] if node.module else base)
        else:
            pkg = node.module or ""
        subs = [f"{pkg}.{a.name}" for a in node.names if f"{pkg}.{a.name}" in known]
        names = subs if len(subs) == len(node.names) else [*subs, pkg]
    out = []
    for name in names:
        while name and name not in known:  # import a.b.c of a non-module attribute path: the module it is in
            name = name.rpartition(".")[0]
        if name:
            out.append(name)
    return out


def import_graph() -> dict[str, dict[str, int]]:
    """``{module: {imported module: line}}`` over the source tree (every import statement, wherever it is)."""
    sources = _sources()
    known = set(sources)
    graph: dict[str, dict[str, int]] = {}
    for module, path in sources.items():
        edges = graph.setdefault(module, {})
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in _imports(tree):
            for target in _targets(node, module, path.name == "__init__.py", known):
                if target != module and not module.startswith(target + "."):
                    edges[target] = min(edges.get(target, node.lineno), node.lineno)
    return graph


def _imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement of a module, wherever it stands (``if TYPE_CHECKING:`` included)."""
    return [node for node in ast.walk(tree) if isinstance(node, ast.Import | ast.ImportFrom)]


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:  # iterative: the graph is deep enough to matter for recursion limits
        work = [(v, iter(graph.get(v, ())))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(graph.get(nxt, ()))))
                elif nxt in on:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _show(graph: dict[str, dict[str, int]], comp: list[str]) -> str:
    members = set(comp)
    edges = [f"{a} -> {b} (line {line})" for a in comp for b, line in sorted(graph[a].items()) if b in members]
    return "; ".join(edges)


def test_the_graph_sees_the_source_tree():
    """The checker itself: it finds modules and their imports, deferred ones too, and it reports a circle."""
    graph = import_graph()
    assert {"station.engine.session", "station.drivers.canopen.robot", "station.mocks.launch",
            "station.procedures.zero_offsets", "station.cli.solve_cmd"} <= set(graph)
    assert "station.robot.base" in graph["station.drivers.canopen.robot"]
    assert "station.cli.nextstep" in graph["station.cli.run_cmd"]  # an import inside a function counts
    assert "station.kinematics" in graph["station.tui.hold"]  # and one under TYPE_CHECKING
    assert "station.cli" not in graph["station.cli.group"]  # its own package: loaded first anyway
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b": 1}, "b": {}}) == []


def test_no_import_circle():
    graph = import_graph()
    found = cycles(graph)
    assert found == [], "\n".join(_show(graph, c) for c in found)
