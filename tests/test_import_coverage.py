"""Every source module has a test that imports it: the modules of ``station/``, ``drivers/``, ``mocks/`` and
``procedures/`` against the imports written in the test files (their ASTs, module level and inside functions).

A module counts as covered when a test file names it in an import: ``import M``, ``from M import name``,
``from P import m`` with ``m`` a submodule of ``P``, or ``from P import name`` where package ``P`` re-exports
``name`` from ``M`` (``from M import name`` in its ``__init__``, or the name -> module table of a lazy package,
``station.lazy.lazy_names``). Importing a package does not cover its submodules. ``M.__main__`` counts as
covered when a test runs ``python -m M``. A module that only re-exports (docstring, imports, ``__all__``: a
package's ``__init__.py``, a command-line name for a shared module) has nothing of its own to test.

Run ``python tests/test_import_coverage.py`` for the list of modules no test imports."""

from __future__ import annotations

import ast
import functools
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"station": "station", "drivers": "station.drivers", "mocks": "station.mocks",
           "procedures": "station.procedures"}
TESTS = ROOT / "tests"


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = [FOLDERS[rel.parts[0]], *rel.parts[1:]]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _only_reexports(tree: ast.Module) -> bool:
    """Docstring, imports and ``__all__``: nothing that runs when used."""
    for i, node in enumerate(tree.body):
        if i == 0 and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            continue
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if all(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                continue
        return False
    return True


@functools.lru_cache(maxsize=1)
def _source_modules() -> frozenset[str]:
    return frozenset(source_modules())


def source_modules() -> set[str]:
    """Import names of the source modules that have code of their own."""
    out = set()
    for folder in FOLDERS:
        for path in (ROOT / folder).rglob("*.py"):
            if any(part.startswith(".") or part == "__pycache__" for part in path.relative_to(ROOT).parts):
                continue
            if _only_reexports(ast.parse(path.read_text(), str(path))):
                continue
            out.add(_module_name(path))
    return out


def _package_path(name: str) -> Path | None:
    # the longest prefix: station.drivers.x lives in drivers/, not station/drivers/
    for folder, prefix in sorted(FOLDERS.items(), key=lambda kv: -len(kv[1])):
        if name == prefix or name.startswith(prefix + "."):
            path = ROOT / folder / Path(*name[len(prefix) + 1:].split(".")) / "__init__.py"
            return path if path.is_file() else None
    return None


@functools.cache
def reexports(package: str) -> dict[str, str]:
    """name -> defining module for the names a package's ``__init__`` takes from elsewhere."""
    path = _package_path(package)
    if path is None:
        return {}
    out = {}
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from .x import n
                base = ".".join([*package.split(".")[:len(package.split(".")) - node.level + 1], *filter(None, [base])])
            for alias in node.names:
                out[alias.asname or alias.name] = base
        elif isinstance(node, ast.Dict):  # a lazy package's table, in one of its three shapes
            for k, v in zip(node.keys, node.values, strict=True):
                if not (isinstance(k, ast.Constant) and isinstance(k.value, str)):
                    continue
                names = [e.value for e in getattr(v, "elts", []) if isinstance(e, ast.Constant)]
                if k.value.startswith(package + "."):  # "module": ("name", ...)
                    out.update({n: k.value for n in names if isinstance(n, str)})
                    continue
                if isinstance(v, ast.Tuple) and v.elts:  # "name": ("module", "attr")
                    v = v.elts[0]
                if isinstance(v, ast.Constant) and isinstance(v.value, str) and v.value.startswith(package + "."):
                    out[k.value] = v.value  # "name": "module"
    return out


def _imports(tree: ast.AST, modules: set[str]) -> set[str]:
    """Source modules named by the imports (and ``-m M`` command lines) in one test file."""
    named = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            named.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            named.add(node.module)
            named.update(f"{node.module}.{alias.name}" for alias in node.names)
            table = reexports(node.module)
            for alias in node.names:
                origin, seen = table.get(alias.name), 0
                while origin and seen < 5:  # a package re-exporting a package's re-export
                    named.add(origin)
                    origin, seen = reexports(origin).get(alias.name), seen + 1
        elif isinstance(node, ast.List | ast.Tuple):
            items = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
            named.update(f"{m}.__main__" for flag, m in zip(items, items[1:], strict=False)
                         if flag == "-m" and isinstance(m, str))
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and getattr(node.func, "attr", getattr(node.func, "id", "")) in ("import_module", "run_module")):
            named.add(node.args[0].value)  # importlib.import_module("M") / runpy.run_module("M")
    return named & modules


def covered(modules: set[str]) -> dict[str, set[str]]:
    """module -> test files (paths relative to tests/) that import it."""
    return {m: set(files) for m, files in _covered(frozenset(modules)).items()}


@functools.lru_cache(maxsize=2)
def _covered(modules: frozenset[str]) -> dict[str, set[str]]:
    by = {m: set() for m in modules}
    for path in TESTS.rglob("*.py"):
        tree = ast.parse(path.read_text(), str(path))
        for m in _imports(tree, modules):
            by[m].add(str(path.relative_to(TESTS)))
    return by


def uncovered() -> list[str]:
    modules = set(_source_modules())
    return sorted(m for m, files in covered(modules).items() if not files)


def test_the_walker_sees_the_source_tree():
    modules = set(_source_modules())
    # the walker must find the big parts; a path rule gone wrong would leave it with nothing to check
    for known in ("station.kinematics.chain", "station.drivers.ur.robot", "station.mocks.world.world",
                  "station.procedures.zero_offsets", "station.cli"):
        assert known in modules, known
    assert len(modules) > 100
    by = covered(modules)
    # this file imports nothing from the source tree: it must not count itself
    assert all("test_import_coverage.py" not in files for files in by.values())


def test_import_forms_are_recognised():
    modules = {"station.a", "station.a.b", "station.c", "station.d.__main__", "station.e"}
    # (these names are not real packages: no re-export table applies)
    code = ("import station.a\nfrom station.a import b\nfrom station import c\n"
            "def f():\n    from station.e import thing\n"
            "CMD = ['python', '-m', 'station.d']\n")
    assert _imports(ast.parse(code), modules) == modules
    assert _imports(ast.parse("import station\nfrom station.x import a\n"), modules) == set()


def test_reexported_names_cover_their_defining_module():
    modules = source_modules()
    # station.solver is a lazy package (name -> module table); station.drivers.ur re-exports with from-imports
    assert "station.solver.estimator" in _imports(ast.parse("from station.solver import solve"), modules)
    assert "station.drivers.ur.robot" in _imports(ast.parse("from station.drivers.ur import URRobot"), modules)
    assert "station.drivers.ur.robot" not in _imports(ast.parse("import station.drivers.ur"), modules)
    # station.mocks.world: name -> (module, attr); station.instruments: module -> names
    assert "station.mocks.world.world" in _imports(ast.parse("from station.mocks.world import World"), modules)
    assert "station.instruments.base" in _imports(ast.parse("from station.instruments import InstrumentBase"),
                                                  modules)


# Not imported by a test yet, and why. An entry leaves this table when a test imports the module (the test below
# fails on a stale entry), never by being ignored.
PENDING: dict[str, str] = {}


def test_every_source_module_is_imported_by_a_test():
    missing = set(uncovered())
    new = sorted(missing - set(PENDING))
    assert not new, (f"{len(new)} source modules no test imports (write tests/test_<part>_<module>.py that imports "
                     f"and tests each): {', '.join(new)}")
    stale = sorted(set(PENDING) - missing)
    assert not stale, f"imported by a test now: remove from PENDING: {', '.join(stale)}"


if __name__ == "__main__":
    mods = source_modules()
    left = uncovered()
    print(f"{len(mods) - len(left)} of {len(mods)} source modules imported by a test; {len(left)} not:")
    print("\n".join(left), file=sys.stdout)
