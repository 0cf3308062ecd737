"""What procedures declare (``station.engine.declare``): every shipped procedure declares its measurements and
options; the declaration is what the procedure really measures (read from its source, independently of the
declaration); the limits file is held to it before the robot opens; ``station run`` takes its procedure flags from
the declarations and ``station run PROC --help`` lists them."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml
from clirunner import station_main

from station.engine.declare import CONSISTENCY, PLAN_OPTIONS, SOLVE, WRITE_BACK, Measurement, measures
from station.engine.limits import LimitsError, check_limits, default_limits, load_limits
from station.engine.procedure import ProcedureError, load_procedure, shipped_folder, shipped_names

# the flags station run took before procedures declared them: a public interface, names and defaults unchanged
RUN_FLAGS = {"--robot", "--serial", "--limits", "--db", "--apply", "--cell", "--operator", "--touch", "--reference",
             "--poses", "--holdout", "--cone", "--seed", "--tracker", "--grid", "--span-deg", "--calibration",
             "--payload", "--identify", "--cycles", "--cube", "--plane", "--quiet", "-q"}


def _measured_in_source(path: Path) -> set[str]:
    """The measurement names a procedure file journals: literal ``s.measure("name", ...)``, the engine's standard
    sets it calls (``measure_result``, ``measure_consistency``), and names built from a literal table
    (iso9283's ``JUDGED``: ``NAME``, ``NAME_nominal``). Read from the syntax tree, not from the declaration."""
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        if node.func.attr == "measure_result":
            names |= {"samples", "fit_rms", "fit_max", "identified", "holdout_rms", "holdout_max", "offset_abs_max",
                      "offset_std_max"}
        elif node.func.attr == "measure_consistency":
            names |= {"samples", "verify_rms", "verify_max"}
        elif node.func.attr == "write_back":
            names.add("writeback_check")
        elif node.func.attr == "measure" and node.args:
            first = node.args[0]
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                names.add(first.value)
            elif isinstance(first, ast.IfExp):
                names |= {b.value for b in (first.body, first.orelse) if isinstance(b, ast.Constant)}
            elif isinstance(first, ast.JoinedStr):  # f"{name}_upper" over a literal tuple in the same loop
                names.add("<f-string>")
    return names


@pytest.mark.parametrize("name", shipped_names())
def test_every_shipped_procedure_declares_what_it_measures(name):
    proc = load_procedure(name)
    assert proc.measurements is not None and proc.options is not None, f"{name} declares nothing"
    declared = {m.name for m in proc.measurements}
    found = _measured_in_source(proc.path)
    literal = found - {"<f-string>"}
    assert literal <= declared, f"{name} measures {sorted(literal - declared)} without declaring them"
    if "<f-string>" in found:  # iso9283: the judged figures, their nominal twins and the intervals' tops
        table = [n for n, _ in proc.module.JUDGED]
        assert {*table, *(f"{n}_nominal" for n in table), "AP_p_upper", "RP_l_upper"} <= declared
    for m in proc.measurements:
        assert m.quantity in ("length", "angle", "number") and m.doc


@pytest.mark.parametrize("name", shipped_names())
def test_the_shipped_limits_meet_every_declaration(name):
    proc = load_procedure(name)
    check_limits(name, proc.measurements, load_limits(None))  # raises on the first mismatch
    judged = {m.name for m in proc.measurements if m.judged}
    sections = [t[name] for t in load_limits(None).models.values() if name in t]
    assert sections, f"limits.yaml has no section for {name}"
    for section in sections:  # judged means: every section gives it a limit
        assert judged <= set(section)


def _limits_without(tmp_path, model: str, procedure: str, drop: str | None = None, add: dict | None = None) -> Path:
    doc = yaml.safe_load(default_limits().read_text())
    section = doc["models"][model][procedure]
    if drop:
        del section[drop]
    section.update(add or {})
    p = tmp_path / "limits.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def test_a_missing_limit_is_one_line_before_the_robot_opens(tmp_path):
    lim = _limits_without(tmp_path, "omx", "zero_offsets", drop="fit_rms")
    with pytest.raises(LimitsError, match=r"models\.omx\.zero_offsets: no limit for fit_rms"):
        check_limits("zero_offsets", load_procedure("zero_offsets").measurements, load_limits(lim))
    # nobody answers at this address: an error naming the limit proves it came before the robot was opened
    code, out, err = station_main("run", "zero_offsets", "--robot", "ur://127.0.0.250", "--serial", "S",
                              "--limits", lim)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("station: error: limits file") and "no limit for fit_rms (mm: RMS" in lines[0]


def test_a_limit_the_procedure_does_not_measure_or_in_another_quantity_is_refused(tmp_path):
    measurements = load_procedure("verify").measurements
    typo = _limits_without(tmp_path, "*", "verify", add={"verify_rsm": {"high": 0.1, "unit": "mm"}})
    with pytest.raises(LimitsError, match=r"models\.\*\.verify\.verify_rsm: procedure verify measures no 'verify_rsm'"):
        check_limits("verify", measurements, load_limits(typo))
    wrong = _limits_without(tmp_path, "*", "verify", add={"verify_max": {"high": 0.1, "unit": "deg"}})
    with pytest.raises(LimitsError, match="the limit is in deg .angle. but verify_max is a length"):
        check_limits("verify", measurements, load_limits(wrong))


def test_a_declaration_that_contradicts_itself_is_refused():
    with pytest.raises(Exception, match="judged but not measured: nope"):
        measures(Measurement("a", "mm", "a length"), judged=("nope",))
    with pytest.raises(Exception, match="measured twice: a"):
        measures(Measurement("a", "mm", "x"), Measurement("a", "deg", "y"))


def test_a_procedure_file_with_a_broken_declaration_names_its_file(tmp_path):
    p = tmp_path / "mine.py"
    p.write_text('"""Mine."""\nfrom station.engine.declare import Measurement, measures\n\n\n'
                 '@measures(Measurement("a", "furlong", "x"))\ndef checklist(s):\n    pass\n')
    proc = load_procedure(p)  # the unit is checked where it is used: the limits and the help
    with pytest.raises(Exception, match="furlong"):
        _ = proc.measurements[0].quantity
    p.write_text('"""Mine."""\n\n\ndef checklist(s):\n    pass\n\n\nchecklist.measurements = ["a"]\n')
    with pytest.raises(ProcedureError, match="mine.py: checklist.measurements must be declared with @measures"):
        load_procedure(p)


def test_run_takes_every_flag_it_took_with_the_declared_ones_from_the_declarations():
    from station.cli.docgen import commands
    from station.cli.procedure_options import declared_flags

    run = dict(commands())["station run"]
    flags = {o: p for p in run.params for o in [*getattr(p, "opts", []), *getattr(p, "secondary_opts", [])]}
    assert set(flags) >= RUN_FLAGS, sorted(RUN_FLAGS - set(flags))
    for option, _ in declared_flags():  # one parameter per declaration, same flag, no default of its own
        assert option.flag in flags and flags[option.flag].default is None
        assert flags[option.flag].help.startswith(option.doc)
    assert {o.flag for o, _ in declared_flags()} >= {o.flag for o in PLAN_OPTIONS} | {"--grid", "--tracker"}


def test_a_flag_the_procedure_does_not_take_is_one_line():
    code, _, err = station_main("run", "zero_offsets", "--robot", "ur://127.0.0.250", "--serial", "S",
                            "--grid", "3")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "--grid: procedure zero_offsets takes no --grid" in lines[0], err
    code, _, err = station_main("run", "correction_map", "--robot", "ur://127.0.0.250", "--serial", "S",
                            "--grid", "0")
    assert code == 2 and "--grid 0: expected sub-intervals 1..100" in err, err


def test_run_procedure_help_lists_its_options_with_units_and_defaults():
    code, out, _ = station_main("run", "correction_map", "--help")
    assert code == 0
    own = out.split("Options of correction_map:")[1].split("Measurements of")[0]
    flat = " ".join(own.split())
    assert "--grid <int> Q sub-intervals per actuator (Q+1 levels). Unit: count; default: 2." in flat
    assert "--span-deg <str>" in flat and "Unit: deg; default: 20." in flat
    assert "--holdout <int>" in flat and "default: 12." in flat  # the procedure's DEFAULTS
    assert "--cone <" not in out and "--cycles <" not in out  # what it does not take is not offered
    meas = " ".join(out.split("Measurements of correction_map")[1].split())
    assert "holdout_rms [mm, judged]" in meas and "tracker_noise_rms [mm]" in meas
    code, out, _ = station_main("run", "--robot", "ur://x", "zero_offsets", "--help")  # after an option
    assert code == 0 and "Options of zero_offsets:" in out and "--tracker <" not in out
    assert "fit_rms [mm, judged]" in " ".join(out.split()) and "offset_std_max [deg]" in " ".join(out.split())
    code, out, _ = station_main("run", "--help")  # no procedure: every flag, which procedures take it
    assert code == 0 and "--tracker <" in out and "--poses <" in out and "Options of" not in out


def test_engine_sets_name_what_the_engine_measures():
    """SOLVE and CONSISTENCY against the engine's own measure calls (read from its source)."""
    engine = Path(__file__).resolve().parents[2] / "station" / "engine"
    measured = set()
    for module in ("session.py", "writeback.py"):
        src = ast.parse((engine / module).read_text())
        measured |= {n.args[0].value for n in ast.walk(src) if isinstance(n, ast.Call)
                     and isinstance(n.func, ast.Attribute) and n.func.attr == "measure" and n.args
                     and isinstance(n.args[0], ast.Constant)}
    assert measured == {m.name for m in (*SOLVE, *CONSISTENCY, *WRITE_BACK)}


def test_shipped_folder_is_where_the_procedures_are():
    assert {p.stem for p in shipped_folder().glob("*.py") if not p.stem.startswith("_")} == set(shipped_names())


def test_a_session_measures_only_what_its_procedure_declares():
    """``Session.measure`` on a session whose procedure declares: an undeclared name or another quantity is one
    line naming the procedure; a declared one is journaled (the journal here: a list)."""
    from types import SimpleNamespace

    from station.engine.session import Session
    from station.robot.errors import ConfigError

    journaled = []
    s = SimpleNamespace(declared={m.name: m for m in SOLVE}, limits={}, measurements=[],
                        journal=SimpleNamespace(header=SimpleNamespace(procedure="mine")), event=journaled.append)
    with pytest.raises(ConfigError, match="procedure mine: measures 'fit_rmss' .length., which it does not declare"):
        Session.measure(s, "fit_rmss", 1e-4)
    with pytest.raises(ConfigError, match="measures 'fit_rms' .angle., declared as a length .mm."):
        Session.measure(s, "fit_rms", 1e-4, "angle")
    assert journaled == []
    Session.measure(s, "fit_rms", 1e-4)
    assert journaled[0]["name"] == "fit_rms" and journaled[0]["value"] == pytest.approx(0.1)  # shown in mm


SITE_PROCEDURE = '''"""My check: touch the socket a few times and judge the spread."""
from station.engine.declare import HOLDOUT, POSES, Measurement, Option, count, measures, takes

DEFAULTS = {"passes": 3}
PASSES = Option("passes", "--passes", count(1, 20), "Passes over every point.", "count")


@measures(Measurement("spread_max", "mm", "largest spread"))
@takes(POSES, HOLDOUT, PASSES)
def checklist(s):
    pass
'''


@pytest.fixture
def handed_over(monkeypatch):
    """``station run`` up to the hand-over to the engine: the options it would start the session with, as the
    one-line error of a stand-in for ``station.api.run`` (nothing is opened)."""
    import station.api
    from station.robot.errors import ConfigError

    def stand_in(procedure, robot, serial, *, options=None, **kw):
        raise ConfigError(f"handed over {procedure.name}: {sorted(options.items())}")

    monkeypatch.setattr(station.api, "run", stand_in)


def test_declared_values_reach_the_session_options(handed_over):
    code, _, err = station_main("run", "correction_map", "--robot", "ur://127.0.0.250", "--serial", "S",
                            "--grid", "3", "--span-deg", "0.1rad", "--tracker", "tcp://127.0.0.1:5300", "--seed", "4")
    assert code == 2 and "handed over correction_map: [('grid', 3), ('seed', 4), ('span_deg', 5.7295" in err, err
    assert "('tracker', 'tcp://127.0.0.1:5300')" in err


def test_a_site_procedure_declares_flags_of_its_own(tmp_path, monkeypatch, handed_over):
    (tmp_path / "my_check.py").write_text(SITE_PROCEDURE)
    monkeypatch.setenv("STATION_PROCEDURES", str(tmp_path))
    base = ["run", "my_check", "--robot", "ur://127.0.0.250", "--serial", "S"]
    code, _, err = station_main(*base, "--passes", "5", "--poses", "7")
    assert code == 2 and "handed over my_check: [('n_fit', 7), ('passes', 5)]" in err, err
    code, _, err = station_main(*base, "--passes", "50")
    assert code == 2 and err.strip() == "station: error: --passes 50: expected an integer 1..20", err
    code, _, err = station_main(*base, "--cone", "30deg")
    assert code == 2 and "--cone: procedure my_check takes no --cone (its options: --holdout, --passes, --poses)" in err
    code, out, _ = station_main("run", "my_check", "--help")
    flat = " ".join(out.split())
    assert code == 0 and "--passes <int> Passes over every point. Unit: count; default: 3." in flat
    code, _, err = station_main("run", "zero_offsets", "--robot", "ur://127.0.0.250", "--serial", "S",
                            "--passes", "5")  # not a flag of a procedure that does not declare it
    assert code == 2 and err.strip().splitlines() == [
        "station: error: --passes: procedure zero_offsets takes no --passes (its options: --cone, --holdout, --poses, "
        "--reference, --seed; station run's own: station run --help)"], err
