"""A resume holds the journal's options to the declarations (``station.engine.declare``: the engine's session
options, the plan's, the procedure's ``@takes`` options and settings): a value a declaration refuses is one line
``station: error: journal PATH:1: field options.NAME: ...``, exit 2, before the robot is opened. One rule per
option: what ``station run`` reads from a flag is what a resume accepts from a journal."""

from __future__ import annotations

import pytest
from clirunner import station_main

from station.engine import events as ev
from station.engine.declare import PLAN_OPTIONS, SESSION_OPTIONS, session_options
from station.engine.journal import Journal
from station.engine.limits import load_limits
from station.engine.procedure import load_procedure, shipped_names

# a robot URL nobody serves: a resume that passes every journal check stops at opening it
NOWHERE = "dynamixel:///dev/does-not-exist?model=omx"


def _plant(home, procedure: str, options: dict) -> str:
    """A journal of ``procedure`` as shipped now (name, sha256, limits), interrupted, with ``options``."""
    path = home / "sessions" / "S-1" / "journal.jsonl"
    Journal.create(path, ev.Header(
        session="S-1", procedure=procedure, procedure_path=f"{procedure}.py",
        procedure_sha256=load_procedure(procedure).sha256, serial="X", url=NOWHERE, options=options,
        limits={"path": None, "version": load_limits(None).version, "sha256": load_limits(None).sha256})).close()
    return str(path)


@pytest.mark.parametrize("procedure, options, says", [
    ("zero_offsets", {"n_holdout": "4"}, "field options.n_holdout: '4' is not an integer 0..100000"),
    ("zero_offsets", {"cone_deg": 1e308}, "field options.cone_deg: '1e+308' is not a half-angle in (0, 90] deg"),
    ("zero_offsets", {"reference": "surveyed"}, "field options.reference: 'surveyed' is not one of unknown, cell"),
    ("zero_offsets", {"touch": "poke"}, "field options.touch: 'poke' is not one of seat, guarded, manual"),
    ("zero_offsets", {"apply": "yes"}, "field options.apply: 'yes' is not true or false"),
    ("zero_offsets", {"roll_deg": 400}, "field options.roll_deg: '400' is not degrees in [0, 360]"),
    ("zero_offsets", {"plan_noise_m": 0}, "field options.plan_noise_m: '0' is not metres in (0, 0.01]"),
    ("correction_map", {"grid": 0}, "field options.grid: '0' is not an integer 1..100"),
    ("correction_map", {"mesh": "hex"}, "field options.mesh: 'hex' is not one of grid, simplex"),
    ("correction_map", {"tracker": "127.0.0.1:5300"}, "field options.tracker: '127.0.0.1:5300' is not a URL"),
    ("correction_map", {"payload": {"mass": -1, "com": [0, 0, 0]}}, "field options.payload: "),
    ("correction_map", {"calibration": ""}, "field options.calibration: '' is not a file name"),
    ("iso9283", {"cycles": 3}, "field options.cycles: '3' is not an integer 4..1000"),
    ("iso9283", {"cube": [0.4, 0, 0.5, -0.3]}, "field options.cube: '[0.4, 0, 0.5, -0.3]' is not [x, y, z, edge]"),
    ("iso9283", {"plane": "w+"}, "field options.plane: 'w+' is not one of x+"),
])
def test_a_journaled_option_a_declaration_refuses_is_one_line(tmp_path, procedure, options, says):
    path = _plant(tmp_path / "home", procedure, options)
    r = station_main("resume", "S-1", env={"STATION_HOME": str(tmp_path / "home")})
    assert r.code == 2 and r.error_line().startswith(f"station: error: journal {path}:1: {says}"), r.err


def test_options_the_declarations_accept_pass_to_the_robot(tmp_path):
    """Every check passed: the resume gets as far as the robot (which is not there)."""
    _plant(tmp_path / "home", "correction_map", {"grid": 3, "mesh": "grid", "n_holdout": 12, "seed": 4,
                                                 "span_deg": 20.0, "tracker": "tcp://127.0.0.1:5300",
                                                 "payload": {"mass": 0.5, "com": [0, 0, 0.03]}, "apply": False,
                                                 "per_socket": "undeclared: not the station's to judge"})
    r = station_main("resume", "S-1", env={"STATION_HOME": str(tmp_path / "home")})
    assert r.code == 2 and "field options" not in r.err and "does-not-exist" in r.error_line(), r.err


# what station run gives each declared flag (typer has made a count an int)
GIVEN = {"n_fit": 12, "n_holdout": 0, "cone_deg": "0.5rad", "seed": 7, "reference": "cell", "touch": "seat",
         "apply": True, "grid": 3, "span_deg": "20deg", "tracker": "tcp://h:1", "payload": "250g@0,0,30mm",
         "cycles": 30, "cube": "400,0,500,300mm", "plane": "z-"}


def test_what_a_flag_reads_is_what_a_resume_accepts():
    """The two rules of each declaration agree: ``holds(read(flag value))`` for every option a shipped procedure
    takes (a calibration file needs a file: its value is a path)."""
    seen = set()
    for name in shipped_names():
        proc = load_procedure(name)
        for o in session_options(proc.module.checklist).values():
            seen.add(o.name)
            if o.name == "calibration":
                assert o.holds("/tmp/result.json") and not o.holds(3)
            elif o.name in GIVEN:
                assert o.holds(o.read(GIVEN[o.name])), (name, o.name)
            assert not o.holds(object()), o.name
    assert {o.name for o in (*SESSION_OPTIONS, *PLAN_OPTIONS)} <= seen
    assert {"grid", "mesh", "tracker", "payload", "calibration", "cycles", "cube", "plane"} <= seen


def test_station_run_reads_touch_by_the_same_declaration():
    """``--touch`` is read by ``declare.TOUCH`` (the resume above holds the journaled value to it too): one line
    before any robot is opened."""
    r = station_main("run", "zero_offsets", "--robot", NOWHERE, "--serial", "S", "--touch", "poke")
    assert r.code == 2 and r.error_line() == "station: error: --touch 'poke': expected one of seat, guarded, manual"
