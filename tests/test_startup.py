"""Start-up of the ``station`` command is guarded by WHAT it imports, not by wall time (timings: bench/startup.py).

Each case runs the real console entry in a fresh interpreter and lists the modules it loaded; ground truth for the
command table is what each command module registers on a real Typer app."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from station.cli import COMMANDS, load_commands

PROBE = textwrap.dedent("""
    import json, sys
    sys.argv = ["station", *json.loads(sys.argv[1])]
    from station.cli import main
    try:
        main()
    except SystemExit:
        pass
    finally:
        sys.stdout.flush()
        sys.stderr.write("\\nMODULES " + json.dumps(sorted(sys.modules)) + "\\n")
""")


def loaded(args: list[str]) -> set[str]:
    import json

    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(args)], capture_output=True, text=True,
                         timeout=120)
    line = [x for x in out.stderr.splitlines() if x.startswith("MODULES ")]
    assert line, out.stderr
    return set(json.loads(line[-1][len("MODULES "):]))  # every module, packages and submodules by full name


HEAVY = ("rich", "textual", "sqlalchemy", "scipy", "matplotlib", "jinja2", "starlette", "uvicorn", "asyncua",
         "can", "canopen", "dynamixel_sdk", "serial", "rtde_control", "psycopg")


def test_help_imports_no_command_module_and_nothing_heavy():
    mods = loaded(["--help"])
    assert not {mod for mod, _ in COMMANDS.values()} & mods
    assert not [m for m in mods if m.startswith("station.cli.") and m not in ("station.cli.__main__",
                                                                               "station.cli.group")]
    assert not set(HEAVY + ("numpy", "pydantic", "yaml")) & mods


def test_fk_with_a_builtin_model_imports_only_what_it_uses(tmp_path):
    joints = tmp_path / "q.csv"
    joints.write_text("q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad]\n0.1,-1.2,1.5,-1.9,-1.57,0.4\n")
    mods = loaded(["fk", "--model", "ur5e", "--joints", str(joints)])
    assert "station.cli.solve_cmd" in mods and "numpy" in mods  # it did run
    others = {mod for mod, _ in COMMANDS.values()} - {"station.cli.solve_cmd"}
    assert not others & mods
    assert not set(HEAVY) & mods
    assert "station.kinematics.modelschema" not in mods  # a built-in model: no schema check at run time


def test_solve_imports_no_scipy_rich_or_database(tmp_path):
    samples = tmp_path / "s.csv"
    samples.write_text("q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad],point\n0.1,-1.2,1.5,-1.9,-1.57,0.4,A\n")
    mods = loaded(["solve", "--model", "ur5e", "--samples", str(samples)])  # too few samples: exit 1 or 2
    assert "station.cli.solve_cmd" in mods
    assert not set(HEAVY) & mods


@pytest.mark.parametrize("module", sorted({mod for mod, _ in COMMANDS.values()}))
def test_command_table_matches_what_each_module_registers(module):
    """station --help lists COMMANDS without importing the modules: the table must say what they define."""
    registered = load_commands(module)
    in_table = {name for name, (mod, _) in COMMANDS.items() if mod == module}
    assert set(registered) == in_table
    for name in in_table:
        assert registered[name].get_short_help_str(limit=1000) == COMMANDS[name][1]


def test_a_model_file_is_still_checked_by_the_strict_schema(tmp_path):
    """Only shipped models skip the schema at run time; a file from outside still gets file:line:field."""
    from station.kinematics import ModelFileError, load_model

    f = tmp_path / "m.yaml"
    f.write_text("format: station-model/1\nconvention: dh\nunits: {length: m, angle: rad}\njoints:\n"
                 "  - limits: [-1, 1]\n    dh: {a: 0.1, alfa: 0}\n")
    with pytest.raises(ModelFileError, match=r"m\.yaml:6: .*alfa"):
        load_model(str(f))


def test_every_builtin_model_passes_the_strict_schema():
    """The check the run time skips for shipped models, done here on each of them."""
    from station.kinematics.catalog import builtin_names, builtin_text
    from station.kinematics.modelfile import ModelFileError
    from station.kinematics.modelschema import check_schema
    from station.yamlfile import parse_yaml_doc

    names = builtin_names()
    assert "ur5e" in names
    for name in names:
        check_schema(parse_yaml_doc(builtin_text(name), ModelFileError, name), ModelFileError)
