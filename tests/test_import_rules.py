"""The import rules of docs/architecture.md, checked on the source: every ``import`` in every module (module
level and inside functions alike: a lazy import is still a dependency) is parsed with ``ast``, and the light
imports are checked in a fresh interpreter's ``sys.modules``."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"station": "station", "drivers": "station.drivers", "mocks": "station.mocks",
           "procedures": "station.procedures"}

# part -> parts it must never import (docs/architecture.md, "Never:" and the table's "may import" column)
NEVER = {
    "station.kinematics": {"station.solver", "station.engine", "station.drivers", "station.mocks", "station.records",
                           "station.report", "station.robot", "station.cli", "station.tui", "station.procedures",
                           "station.instruments"},
    "station.solver": {"station.engine", "station.drivers", "station.mocks", "station.records", "station.report",
                       "station.robot", "station.cli", "station.tui", "station.procedures", "station.instruments"},
    # measuring instruments: like station.robot (its errors and URL options are theirs too), nothing heavier
    "station.instruments": {"station.drivers", "station.mocks", "station.engine", "station.solver",
                            "station.kinematics", "station.records", "station.report", "station.cli", "station.tui",
                            "station.procedures"},
    "station.robot": {"station.drivers", "station.mocks", "station.engine", "station.solver", "station.records",
                      "station.report", "station.cli", "station.tui", "station.procedures"},
    "station.drivers": {"station.engine", "station.cli", "station.tui", "station.records", "station.report",
                        "station.mocks", "station.solver", "station.procedures", "station.api"},
    "station.mocks": {"station.drivers", "station.engine", "station.robot", "station.cli", "station.tui",
                      "station.records", "station.report", "station.solver", "station.procedures", "station.api",
                      "station.instruments"},
    "station.engine": {"station.drivers", "station.mocks", "station.cli", "station.tui"},
    "station.procedures": {"station.drivers", "station.mocks", "station.cli", "station.tui"},
    "station.records": {"station.engine", "station.drivers", "station.mocks", "station.cli", "station.tui"},
    "station.report": {"station.engine", "station.drivers", "station.mocks", "station.cli", "station.tui"},
}
# made true by the journal branch (the runner/CLI hands results to records and report)
ENGINE_LATER = {"station.records", "station.report"}
HEAVY = ("numpy", "scipy", "yaml", "station.kinematics")
BUS_LIBRARIES = ("can", "canopen", "dynamixel_sdk", "serial", "rtde_control", "rtde_receive")
# the station.robot modules drivers use for motion maths: they may load numpy (nothing else in station.robot)
ROBOT_NUMERIC = {"station.robot.motion"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = [FOLDERS[rel.parts[0]], *rel.parts[1:]]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.Module, module: str, is_package: bool):
    """``(imported module, module_level)`` for every import, those under ``if TYPE_CHECKING:`` included (as not
    module level: they are never loaded at run time)."""
    out = []

    def visit(node, top: bool):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                # an annotation's import is a dependency all the same (the layering holds for it), but it is never
                # loaded at run time: not module level for the start-up weight rule
                visit(ast.Module(body=child.body, type_ignores=[]), False)
                visit(ast.Module(body=child.orelse, type_ignores=[]), top)
                continue
            if isinstance(child, ast.Import):
                out.extend((a.name, top) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = module.split(".")
                    base = base[:len(base) - child.level + (1 if is_package else 0)]
                    name = ".".join([*base, child.module] if child.module else base)
                else:
                    name = child.module
                out.append((name, top))
                out.extend((f"{name}.{a.name}", top) for a in child.names)  # from pkg import submodule
            inner = top and not isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            visit(child, inner)

    visit(tree, True)
    return out


def _graph():
    """``[(module, imported, module_level, file, line-less)]`` over the whole source tree."""
    rows = []
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            module = _module_name(path)
            tree = ast.parse(path.read_text(), filename=str(path))
            for name, top in _imports(tree, module, path.name == "__init__.py"):
                rows.append((module, name, top, path.relative_to(ROOT)))
    return rows


def _part(module: str) -> str | None:
    bits = module.split(".")
    if bits[0] != "station":
        return None
    return "station" if len(bits) == 1 else f"station.{bits[1]}"


def _under(name: str, part: str) -> bool:
    return name == part or name.startswith(part + ".")


def _violations(rules: dict[str, set[str]]) -> list[str]:
    bad = []
    for module, name, _top, path in _graph():
        forbidden = rules.get(_part(module), set())
        hit = next((p for p in forbidden if _under(name, p)), None)
        if hit:
            bad.append(f"{path}: {module} imports {name} ({_part(module)} never imports {hit})")
    return sorted(set(bad))


def test_graph_sees_the_source_tree():
    """The checker itself: it finds the modules and the imports it is meant to judge."""
    rows = _graph()
    modules = {m for m, *_ in rows}
    assert {"station.robot.registry", "station.drivers.canopen.robot", "station.mocks.launch",
            "station.engine.runner"} <= modules
    assert ("station.drivers.canopen.robot", "station.robot.base", True) in {(m, n, t) for m, n, t, _ in rows}
    assert _violations({"station.drivers": {"station.robot"}})  # a rule that does not hold is reported
    typing_only = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import station.records\n")
    assert ("station.records", False) in _imports(typing_only, "station.engine.x", False)


def test_parts_never_import_what_the_architecture_forbids():
    rules = {k: (v - ENGINE_LATER if k == "station.engine" else v) for k, v in NEVER.items()}
    assert _violations(rules) == []


def test_engine_does_not_import_records_or_report():
    assert _violations({"station.engine": ENGINE_LATER}) == []


def test_station_robot_imports_nothing_heavy_at_module_level():
    bad = []
    for module, name, top, path in _graph():
        robot_side = _part(module) == "station.robot" and module not in ROBOT_NUMERIC
        if robot_side and top and any(_under(name, h) for h in HEAVY + BUS_LIBRARIES):
            bad.append(f"{path}: {module} imports {name} at module level")
    assert bad == []


def _loaded_after(code: str) -> list[str]:
    probe = (f"import sys\n{code}\nimport json\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
             "('numpy', 'scipy', 'yaml', 'can', 'canopen', 'dynamixel_sdk', 'serial', 'rtde_control', "
             "'rtde_receive') or m.startswith(('station.kinematics', 'station.drivers', 'station.engine', "
             "'station.mocks', 'station.robot')))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)


def test_import_station_robot_loads_no_numpy_kinematics_or_bus_library():
    loaded = _loaded_after("import station.robot.errors\nimport station.robot\n"
                           "from station.robot import ConfigError, Robot, CalibrationStore, FaultRecovery, open_robot\n"
                           "import station.robot.base, station.robot.registry, station.robot.url")
    heavy = [m for m in loaded if not m.startswith("station.robot")]
    assert heavy == [], heavy


def test_import_station_instruments_loads_no_numpy_or_driver():
    loaded = _loaded_after("import station.instruments\nfrom station.instruments import InstrumentBase, PoseReading, "
                           "open_instrument, schemes\nimport station.instruments.base, station.instruments.registry")
    heavy = [m for m in loaded if not m.startswith("station.robot")]
    assert heavy == [], heavy


def test_mocks_load_nothing_from_the_station_side_of_the_wire():
    loaded = _loaded_after("import station.mocks.launch, station.mocks.world, station.mocks.canopen.cli, "
                           "station.mocks.dynamixel.cli, station.mocks.ur.cli, station.mocks.world.cli")
    station_side = [m for m in loaded if m.startswith(("station.robot", "station.drivers", "station.engine"))]
    assert station_side == [], station_side
