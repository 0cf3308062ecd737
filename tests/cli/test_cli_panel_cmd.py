"""``station.cli.panel_cmd``: the panel's files are checked when it starts (one line each), not when the first unit
is scanned; and the options ``station run``, ``station panel`` and ``station opcua`` share
(``station.cli.run_options``, the plan's from the engine's declarations)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from clirunner import station_main

from station.cli import run_options
from station.cli.panel_cmd import _check_files
from station.engine import declare

CELL = ("format: station-cell/1\nunits: {length: mm}\npoints:\n"
        "  A: {kind: socket, position: [350, 0, 750], approach: [0, 0, 1]}\n")


def test_each_bad_file_is_named_at_start(tmp_path):
    cell = tmp_path / "cell.yaml"
    cell.write_text(CELL)
    _check_files(SimpleNamespace(procedure="zero_offsets", limits=None, cell=str(cell)))  # all good
    bad_limits = tmp_path / "limits.yaml"
    bad_limits.write_text("format: nonsense\n")
    for cfg, needle in ((SimpleNamespace(procedure="no_such_proc", limits=None, cell=str(cell)), "no_such_proc"),
                        (SimpleNamespace(procedure="zero_offsets", limits=str(bad_limits), cell=str(cell)),
                         "limits.yaml"),
                        (SimpleNamespace(procedure="zero_offsets", limits=None, cell=str(tmp_path / "none.yaml")),
                         "none.yaml")):
        with pytest.raises(Exception, match=needle) as e:
            _check_files(cfg)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("command", ["run", "panel", "opcua"])
def test_shared_options_are_offered_by_both_commands(command):
    out = " ".join(station_main(command, "--help", columns=200).out.split())
    for opt in (run_options.LIMITS, run_options.DB, run_options.POSES, run_options.HOLDOUT, run_options.CONE,
                run_options.REFERENCE):
        flag = opt.param_decls[0]
        assert flag in out, (command, flag)
    # --reference is the engine's one declaration everywhere: its help, and its reading of a value
    assert declare.REFERENCE.doc in out, command


@pytest.mark.parametrize("command", ["panel", "opcua"])
def test_a_bad_reference_is_refused_by_the_declaration_before_anything_serves(tmp_path, command):
    cell = tmp_path / "cell.yaml"
    cell.write_text(CELL)
    r = station_main(command, "--robot", "ur://127.0.0.1:9", "--cell", cell, "--reference", "surveyed")
    assert r.code == 2 and r.error_line() == ("station: error: --reference 'surveyed': expected "
                                              f"{declare.REFERENCE.kind.form}"), r.err


@pytest.mark.parametrize("command", ["run", "panel"])
def test_touch_is_the_engines_one_declaration(tmp_path, command):
    assert declare.TOUCH.doc in " ".join(station_main(command, "--help", columns=200).out.split()), command
    cell = tmp_path / "cell.yaml"
    cell.write_text(CELL)
    args = ("zero_offsets", "--serial", "U1") if command == "run" else ()
    r = station_main(command, *args, "--robot", "ur://127.0.0.1:9", "--cell", cell, "--touch", "probe")
    assert r.code == 2 and r.error_line() == ("station: error: --touch 'probe': expected "
                                              f"{declare.TOUCH.kind.form}"), r.err
