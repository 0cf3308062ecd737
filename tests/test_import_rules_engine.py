"""Layering as drawn in docs/architecture.md: the engine and the shipped procedures import nothing from the
records, the report, the CLI, the jog UI or a concrete driver (results reach records and report through the
runner/CLI layer: ``station.publish``). Checked on the source (every import statement, also inside functions,
and ``importlib.import_module``/``__import__`` with a literal name) and at run time (what importing every
engine module loads)."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = ("station.records", "station.report", "station.cli", "station.tui", "station.drivers",
             "station.publish", "station.api")
# third-party packages only those layers use: their presence after importing the engine means a leak
FORBIDDEN_LIBS = ("sqlalchemy", "psycopg", "matplotlib", "jinja2", "textual", "typer", "rich")
PACKAGES = {"station.engine": ROOT / "station" / "engine", "station.procedures": ROOT / "procedures"}


def imports_of(source: str, filename: str, package: str) -> list[tuple[int, str]]:
    """``(line, module)`` for every module ``source`` imports; ``from a import b`` yields ``a`` and ``a.b``
    (``b`` may be a sub-module, as in ``from station import records``); relative imports are resolved."""
    out = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            out.append((node.lineno, base))
            out += [(node.lineno, f"{base}.{a.name}") for a in node.names if a.name != "*"]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            fn = node.func
            name = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
            if name in ("import_module", "__import__"):
                out.append((node.lineno, node.args[0].value))
    return out


def violations(source: str, filename: str, package: str) -> list[str]:
    return [f"{filename}:{line}: imports {mod}" for line, mod in imports_of(source, filename, package)
            if any(mod == f or mod.startswith(f + ".") for f in FORBIDDEN)]


def _files():
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            yield pytest.param(package, path, id=str(path.relative_to(ROOT)))


@pytest.mark.parametrize("package,path", list(_files()))
def test_engine_and_procedures_import_no_outer_layer(package, path):
    assert violations(path.read_text(), str(path.relative_to(ROOT)), package) == []


def test_the_check_sees_every_kind_of_import():
    src = ("import station.report\n"
           "from station import records\n"
           "def f():\n    from station.cli.run_cmd import summary\n"
           "from ..tui import app\n"
           "import importlib\nimportlib.import_module('station.drivers.ur')\n"
           "from station.engine import events\nimport numpy\n")
    found = violations(src, "x.py", "station.engine")
    assert sorted(v.split(": imports ")[1] for v in found) == [
        "station.cli.run_cmd", "station.cli.run_cmd.summary", "station.drivers.ur", "station.records",
        "station.report", "station.tui", "station.tui.app"]


def test_importing_the_engine_loads_no_outer_layer():
    modules = [f"station.engine.{p.stem}" for p in sorted(PACKAGES["station.engine"].glob("*.py"))
               if p.stem != "__init__"]
    code = ("import json, sys\n"
            + "".join(f"import {m}\n" for m in modules)
            + "from station.engine import load_procedure, shipped_names\n"
            + "[load_procedure(n) for n in shipped_names()]\n"
            + "print(json.dumps(sorted(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    loaded = json.loads(out.stdout)
    leaks = [m for m in loaded if any(m == f or m.startswith(f + ".") for f in FORBIDDEN + FORBIDDEN_LIBS)]
    assert leaks == []


def test_journal_readers_stay_light():
    """Reading a journal (records, report, tools) needs neither numpy nor the kinematics."""
    code = ("import json, sys\nimport station.engine.session_record, station.units\n"
            "print(json.dumps(sorted(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    loaded = json.loads(out.stdout)
    assert not [m for m in loaded if m.split(".")[0] in ("numpy", "scipy", "yaml")
                or m.startswith(("station.kinematics", "station.robot", "station.solver"))]
