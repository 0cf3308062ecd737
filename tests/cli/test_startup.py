"""Start-up of the ``station`` command is guarded by WHAT it imports, not by wall time (timings: bench/startup.py).

Each case runs the real console entry in a fresh interpreter and lists the modules it loaded; ground truth for the
command table is what each command module registers on a real Typer app."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from clirunner import station_proc

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
                                                                               "station.cli.group",
                                                                               "station.cli.helpgroup")]
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


# what the hot commands never load with a built-in model and a plain CSV (fast start: solve <= 0.3 s end to end):
# typer converts option values through pydantic TypeAdapters; numpy.ma came with np.median; the plan-time
# prediction, TCP methods and IK are other commands' parts; logging and importlib.resources cost start-up only
NOT_ON_THE_HOT_PATH = ("typer", "typer._adapters", "pydantic", "pydantic_core", "rich", "numpy.ma", "logging",
                       "importlib.resources", "station.cli.group", "station.solver.predict", "station.solver.tcp",
                       "station.kinematics.ik", "station.kinematics.modelschema")


def ur5e_touches(path, n: int = 50) -> None:
    """A 12 x 50 touch data set as bench/startup.py writes it (UR5e, hidden offset/TCP errors, 20 um noise)."""
    import numpy as np

    from station.kinematics import load_model
    from station.solver.simulate import noisy_q, touch_q

    rng = np.random.default_rng(1)
    home = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
    nominal = load_model("ur5e").with_params({"tcp.x": 0.02, "tcp.y": -0.01, "tcp.z": 0.12})
    truth = nominal.with_params({x: nominal.param(x) + rng.normal(0, 1e-3) for x in nominal.select("offsets,tcp")
                                 if x not in ("offset.j1", "offset.j6")})
    c = truth.position(home)
    q = noisy_q(truth, touch_q(truth, c, n, rng, centre=home, spread=0.35), np.tile(c, (n, 1)), 20e-6, rng)
    rows = [",".join([*(repr(float(v)) for v in row), "A"]) for row in q]
    path.write_text("q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad],point\n" + "\n".join(rows) + "\n")


def test_a_whole_solve_and_fk_load_no_typer_pydantic_or_numpy_ma(tmp_path):
    from station.kinematics.catalog import _builtin_doc

    samples, out = tmp_path / "s.csv", tmp_path / "r.json"
    ur5e_touches(samples)
    _builtin_doc("ur5e")  # its parse cached (as the first command after an install does): no yaml below
    mods = loaded(["solve", "--model", "ur5e", "--samples", str(samples), "--tool", "0.02,-0.01,0.12",
                   "--out", str(out)])
    import json

    result = json.loads(out.read_text())  # it did solve, to the end
    assert result["solve_time_s"] > 0 and "station.solver.estimator" in mods
    assert not set(NOT_ON_THE_HOT_PATH + ("yaml",)) & mods
    assert not set(HEAVY) & mods
    mods = loaded(["fk", "--model", "ur5e", "--joints", str(samples)])
    assert "station.kinematics.model" in mods
    assert not set(NOT_ON_THE_HOT_PATH + ("yaml",)) & mods


def test_the_console_script_flushes_everything_before_its_fast_exit(tmp_path):
    """After solve/fk ``station.cli.console`` ends the process without the interpreter's teardown: every row is
    still written, the exit code kept, and a failed write of stdout (a full disk) is one line and exit 2."""
    samples = tmp_path / "s.csv"
    ur5e_touches(samples)
    cmd = [sys.executable, "-m", "station.cli", "fk", "--model", "ur5e", "--joints", str(samples)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    rows = [r for r in p.stdout.splitlines() if r and not r.startswith(("#", "x["))]
    assert len(rows) == 50 and all(len(r.split(",")) == 6 for r in rows)
    with open("/dev/full", "w") as full:
        p = subprocess.run(cmd, stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and lines[0].startswith("station: error:"), p.stderr
    assert "No space left on device" in p.stderr
    p = station_proc("solve", "--model", "ur5e", "--samples", samples, "--max-std", "abc", module=True)
    assert p.code == 2 and p.err.count("\n") == 1 and "--max-std" in p.err


def test_shipped_models_parse_alike_with_libyaml():
    """Built-in models are parsed by libyaml (``shipped=True``); the strict pure-Python loader is the reference:
    the same values and the same line of every key and item."""
    from station.kinematics.catalog import builtin_names, builtin_text
    from station.kinematics.modelfile import ModelFileError
    from station.yamlfile import parse_yaml_doc

    for name in builtin_names():
        strict = parse_yaml_doc(builtin_text(name), ModelFileError, name)
        fast = parse_yaml_doc(builtin_text(name), ModelFileError, name, shipped=True)
        assert fast.data == strict.data and fast.lines == strict.lines, name
        assert len(fast.lines) > 20


def test_the_cached_parse_of_a_builtin_model_is_the_parse_and_is_dropped_when_stale():
    """``station.kinematics.catalog._builtin_doc`` keeps libyaml's parse beside the model with the text it came
    from; the strict loader is the reference. A torn, foreign or stale cache is parsed over, never believed."""
    import marshal
    import sys

    from station.kinematics.catalog import _builtin_doc, _models, builtin_names, builtin_text
    from station.kinematics.modelfile import ModelFileError
    from station.yamlfile import parse_yaml_doc

    for name in builtin_names():
        strict = parse_yaml_doc(builtin_text(name), ModelFileError, f"{name} (built-in)")
        for _ in range(2):  # parsed (and kept), then from the cache
            doc = _builtin_doc(name)
            assert (doc.name, doc.data, doc.lines) == (strict.name, strict.data, strict.lines), name
    cache = _models() / "__pycache__" / f"ur5e.{sys.implementation.cache_tag}.marshal"
    strict = parse_yaml_doc(builtin_text("ur5e"), ModelFileError, "ur5e (built-in)")
    assert cache.is_file()
    for bad in (b"\x00torn", marshal.dumps(("an older ur5e.yaml", {"joints": []}, {})), b""):
        cache.write_bytes(bad)
        doc = _builtin_doc("ur5e")
        assert (doc.data, doc.lines) == (strict.data, strict.lines)
        assert marshal.loads(cache.read_bytes())[0] == builtin_text("ur5e")  # rewritten


def test_the_estimators_median_is_numpys():
    """``station.solver.estimator._median`` replaces np.median (which imports numpy.ma) in the outlier test."""
    import numpy as np

    from station.solver.estimator import _median

    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 49, 50, 1001):
        x = rng.lognormal(size=n)
        assert _median(x) == float(np.median(x))
    assert _median(np.array([2.0, 1.0, 1.0, 5.0])) == 1.5
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))


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


def test_main_in_process_leaves_the_callers_process_as_it_was(tmp_path, capsys, monkeypatch):
    """The start-up settings of solve/fk (collector threshold, one BLAS thread) stay inside the command: main()
    run by a script or a test changes neither the collector nor the environment its children inherit."""
    import gc
    import os

    from station.cli import main

    joints = tmp_path / "q.csv"
    joints.write_text("q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad]\n0.1,-1.2,1.5,-1.9,-1.57,0.4\n")
    before, blas = gc.get_threshold(), os.environ.get("OPENBLAS_NUM_THREADS")
    monkeypatch.setattr(sys, "argv", ["station", "fk", "--model", "ur5e", "--joints", str(joints)])
    main()
    assert len(capsys.readouterr().out.splitlines()) == 3
    assert gc.get_threshold() == before and os.environ.get("OPENBLAS_NUM_THREADS") == blas
