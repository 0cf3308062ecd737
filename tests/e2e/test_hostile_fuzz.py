"""Property-based fuzzing (hypothesis) of every reader and of the CLI entry points: whatever the
input — random bytes, random structure, random numbers incl. NaN/inf/huge, random units — the result is a
valid value or the reader's own one-line error; the CLI exits 0 with a valid result or 2 with one line; never
a traceback, never another exception, never a hang (pytest-timeout bounds each test).

The fast subset runs ``FAST`` examples per property; ``-m slow`` runs ``SLOW`` (set HYPOTHESIS_SLOW_EXAMPLES)."""

import contextlib
import copy
import functools
import json
import math
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from clirunner import station_main
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from station.engine.cell import CellError, cell_from_dict
from station.engine.limits import LimitsError, load_limits
from station.kinematics import ModelFileError, dump_model, load_model, model_from_dict
from station.kinematics.parallel import ParallelKinematicsError
from station.robot.errors import ConfigError
from station.samplesfile import SamplesFileError, read_joints, read_samples
from station.yamlfile import parse_yaml_doc

FAST = 40
SLOW = int(os.environ.get("HYPOTHESIS_SLOW_EXAMPLES", "120"))  # in make test; set higher for a campaign
fast = settings(max_examples=FAST, deadline=None, suppress_health_check=[HealthCheck.too_slow])
slow = settings(max_examples=SLOW, deadline=None, suppress_health_check=[HealthCheck.too_slow])

UR5E = load_model("ur5e")
MODEL_DOC = yaml.safe_load(dump_model(UR5E, "mm", "deg"))
CELL_DOC = {"format": "station-cell/1", "units": {"length": "mm", "angle": "deg"},
            "tool": {"z": 100}, "points": [{"label": "A", "kind": "socket", "position": [450, 0, 50],
                                            "approach": [0, 0, 1], "radius": 3}]}
LIMITS_DOC = {"format": "station-limits/1", "version": "1",
              "models": {"*": {"zero_offsets": {"fit_rms": {"high": 0.1, "marginal": 0.06, "unit": "mm"}}}}}

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-(10**60), max_value=10**60),
    st.sampled_from([0, -1, 1, 1e308, -1e308, 1e-320, 2**63, 85.0, 1000.0]),
)
scalars = st.one_of(numbers, st.booleans(), st.none(), st.text(max_size=12),
                    st.sampled_from(["mm", "m", "deg", "rad", "1_0", "\u0661", ".nan", "yes", "on", "1:30", ""]))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                      max_leaves=12)


def _paths(doc, prefix=()):
    """Every path to a value in ``doc`` (mappings and lists)."""
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, prefix + (i,))
    return out


@st.composite
def mutated(draw, base: dict):
    """``base`` with one to three random edits: a value replaced, a key added, a key removed."""
    doc = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p in _paths(doc) if p]
        path = draw(st.sampled_from(paths))
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        what = draw(st.sampled_from(["replace", "add", "remove"]))
        if what == "replace":
            parent[path[-1]] = draw(values)
        elif what == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["alfa", "tol", "radius", "x", "unit", "zero", "extra"]))] = draw(values)
        elif what == "remove" and isinstance(parent, dict):
            parent.pop(path[-1], None)
    return doc


def _yaml(doc) -> str:
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)


def _one_line(e: Exception) -> None:
    assert "\n" not in str(e) and str(e), repr(e)


# ---- the YAML loader ----------------------------------------------------------------------------------------
class Bad(ValueError):
    pass


@fast
@given(st.one_of(st.binary(max_size=300), st.text(max_size=300)))
def test_yaml_loader_random_input(data):
    try:
        doc = parse_yaml_doc(data, Bad, "f.yaml")
    except Bad as e:
        _one_line(e)
        return
    json.dumps(doc.data, allow_nan=True)  # plain data only: dicts, lists, str, int, float, bool, None


@fast
@given(values)
def test_yaml_loader_round_trip(v):
    """Whatever PyYAML writes, the strict loader reads back the same (or refuses it in one line)."""
    try:
        doc = parse_yaml_doc(_yaml({"k": v}), Bad, "f.yaml")
    except Bad as e:
        _one_line(e)
        return
    got = doc.data["k"]
    if isinstance(v, float) and math.isnan(v):
        assert isinstance(got, float) and math.isnan(got)
    elif not isinstance(v, float | dict | list):
        assert got == v or (isinstance(v, str) and got == v)


# ---- model, cell, limits files ------------------------------------------------------------------------------
def _check_model(doc) -> None:
    text = _yaml(doc)
    try:
        m = model_from_dict(parse_yaml_doc(text, ModelFileError, "m.yaml"), "m.yaml")
    except ModelFileError as e:
        _one_line(e)
        return
    assert np.all(np.isfinite(m.params)), "a model read from a file has non-finite parameters"
    assert np.all(np.isfinite(m.fk(np.zeros(m.n_joints))))
    for j in m.joints:
        assert j.max_velocity > 0 and j.lower < j.upper
        if j.encoder:
            assert j.encoder.direction in (1, -1) and j.encoder.gear > 0 and j.encoder.counts_per_unit > 0




def _check_cell(doc) -> None:
    try:
        cell = cell_from_dict(parse_yaml_doc(_yaml(doc), CellError, "c.yaml"), "c.yaml")
    except CellError as e:
        _one_line(e)
        return
    for label, p in cell.points.items():
        assert isinstance(label, str) and label and label != "None"
        assert np.all(np.isfinite(p.position)) and p.radius > 0


# the model and cell readers: FAST examples each in the fast subset, SLOW in the slow one (one test, two sizes)
@pytest.mark.parametrize("check, base", [(_check_model, MODEL_DOC), (_check_cell, CELL_DOC)], ids=["model", "cell"])
@pytest.mark.parametrize("runs", [fast, pytest.param(slow, marks=pytest.mark.slow)], ids=["fast", "long"])
def test_reader_fuzz(check, base, runs):
    runs(given(mutated(base))(check))()


@fast
@given(mutated(LIMITS_DOC))
def test_limits_reader_fuzz(doc):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "limits.yaml"
        f.write_text(_yaml(doc))
        try:
            lim = load_limits(f)
        except LimitsError as e:
            _one_line(e)
            return
    for table in lim.models.values():
        for proc in table.values():
            for limit in proc.values():
                assert all(v is None or math.isfinite(v) for v in (limit.low, limit.high, limit.marginal))


# ---- samples CSV ----------------------------------------------------------------------------------------------
cells = st.one_of(numbers.map(lambda x: repr(x) if not isinstance(x, float) else f"{x!r}"),
                  st.text(alphabet=st.characters(blacklist_categories=["Cs"]), max_size=8),
                  st.sampled_from(["1_0", "\u0661", "nan", "inf", "0x10", "85", "-1e400", "", " 0.1 "]))
headers = st.sampled_from(["q{}", "q{}[deg]", "q{}[rad]", "q{}[mm]", "q{}[furlong]", "q{}[mrad]"])


@st.composite
def csv_text(draw):
    n = draw(st.integers(5, 7))
    head = [draw(headers).format(j + 1) for j in range(n)] + draw(st.sampled_from([[], ["point"], ["x", "y", "z"]]))
    rows = []
    for _ in range(draw(st.integers(0, 6))):
        rows.append([draw(st.one_of(cells, st.floats(-3, 3).map(repr))) for _ in head])
    body = "\n".join(",".join(r) for r in rows)
    return ",".join(head) + "\n" + body + "\n"


@fast
@given(csv_text())
def test_samples_reader_fuzz(text):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "s.csv"
        f.write_text(text, encoding="utf-8")
        for reader in (read_samples, read_joints):
            try:
                out = reader(f, UR5E)
            except SamplesFileError as e:
                _one_line(e)
                continue
            q = out.q if hasattr(out, "q") else out[0]
            assert q.shape[1] == 6 and np.all(np.isfinite(q))
            lo = np.array([j.lower for j in UR5E.joints]) - 0.2
            hi = np.array([j.upper for j in UR5E.joints]) + 0.2
            assert np.all((q >= lo) & (q <= hi)), "a reading beyond the joint limits was accepted"


@fast
@given(st.binary(max_size=400))
def test_samples_reader_random_bytes(data):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "s.csv"
        f.write_bytes(data)
        try:
            read_samples(f, UR5E)
        except SamplesFileError as e:
            _one_line(e)


# ---- CLI entry points -----------------------------------------------------------------------------------------
def _exit_0_or_one_line(code, err):
    assert code in (0, 2), (code, err)
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("station: error: "), err
        assert "internal error" not in err, err


@fast
@given(csv_text())
def test_cli_fk_fuzz(text):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "j.csv"
        f.write_text(text, encoding="utf-8")
        code, out, err = station_main("fk", "--model", "ur5e", "--joints", f)
    _exit_0_or_one_line(code, err)
    if code == 0:
        rows = [r for r in out.splitlines()[2:] if r]
        assert rows and all(math.isfinite(float(v)) for r in rows for v in r.split(","))


@pytest.mark.slow
@slow
@given(csv_text())
def test_cli_fk_fuzz_long(text):
    test_cli_fk_fuzz.hypothesis.inner_test(text)


option_numbers = st.one_of(numbers.map(str), st.sampled_from(["nan", "inf", "-inf", "1e999", "0", "-0", "abc", ""]))


@fast
@given(st.sampled_from(["--poses", "--holdout", "--cone", "--seed", "--touch"]), option_numbers)
def test_cli_run_options_fuzz(option, value):
    """Run options: a bad value is refused in one line before the robot (at an address nobody answers) is opened;
    a good one passes the pre-flight (checked directly, so no bus is waited on)."""
    from station.cli.run_cmd import preflight

    kw = {"poses": None, "holdout": None, "cone": None, "seed": None, "touch": None}
    key = option.removeprefix("--")
    try:
        kw[key] = value if key == "touch" else (float(value) if key == "cone" else int(value))
    except (ValueError, OverflowError):
        code, _, err = station_main("run", "zero_offsets", "--robot", "ur://127.0.0.250", "--serial", "S",
                                      option, value)
        _exit_0_or_one_line(code, err)
        assert code == 2
        return
    try:
        preflight("ur://127.0.0.250", kw["poses"], kw["holdout"], kw["cone"], kw["seed"], kw["touch"], None,
                  None, None)
    except ConfigError as e:
        _one_line(e)
        assert option in str(e)


@fast
@given(option_numbers)
def test_cli_solve_max_std_fuzz(value):
    from station.cli.solve_cmd import check_max_std

    try:
        v = float(value)
    except ValueError:
        return
    try:
        assert check_max_std(v) > 0 and math.isfinite(v)
    except ConfigError as e:
        _one_line(e)


@fast
@given(mutated({"format": "station-calibration/1", "units": "SI (m, rad)", "model": "ur5e",
                "parameters": {"offset.j2": {"value": 0.003, "std": 1e-5, "identifiable": True, "reason": None,
                                             "nominal": 0.0, "kind": "model", "unit": "rad"},
                               "tcp.z": {"value": 0.1, "std": None, "identifiable": False, "reason": "weak",
                                         "nominal": 0.1, "kind": "model", "unit": "m"}},
                "residuals": {}, "rank": 1, "n_parameters": 2, "converged": True, "iterations": 3}))
def test_calibration_reader_fuzz(doc):
    from station.resultfile import load_calibration

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "c.json"
        f.write_text(json.dumps(doc))  # NaN/Infinity written as JSON extensions on purpose
        try:
            m = load_calibration(f, UR5E)
        except ConfigError as e:
            _one_line(e)
            return
    assert np.all(np.isfinite(m.params))


# ---- world files (the emulators' truth) ----------------------------------------------------------------------
def _world_doc() -> dict:
    from station.mocks.world.worldfile import WorldSpec, spec_to_dict

    return yaml.safe_load(yaml.safe_dump(spec_to_dict(WorldSpec(), UR5E, "mm", "deg")))


@fast
@given(mutated(_world_doc()))
def test_world_reader_fuzz(doc):
    from station.mocks.world.worldfile import WorldFileError, spec_from_dict

    try:
        spec = spec_from_dict(parse_yaml_doc(_yaml(doc), WorldFileError, "w.yaml").data, "w.yaml")
    except WorldFileError as e:
        _one_line(e)
        return
    assert spec.seed >= 0 and isinstance(spec.enabled, bool)
    assert all(isinstance(p["label"], str) and p["label"] for p in spec.points)


PARALLEL_DOC = yaml.safe_load(dump_model(load_model("hexapod"), "mm", "deg"))


@fast
@given(mutated(PARALLEL_DOC))
def test_parallel_model_reader_fuzz(doc):
    try:
        m = model_from_dict(parse_yaml_doc(_yaml(doc), ModelFileError, "h.yaml"), "h.yaml")
    except (ModelFileError, ConfigError, ParallelKinematicsError) as e:
        _one_line(e)
        return
    assert m is not None


# ---- every reader through the command line: exit 0/1/2, one line, no internal error, no warning -----------------
# (docs/reliability.md, "No internal error from a file"). In-process CLI (station.cli.main); Python and numpy
# warnings are recorded ("always") and must not occur; every stderr line is the station's own ("station: ...").
def _clean_cli(argv, env: dict | None = None) -> tuple[int, str, str]:
    import warnings
    from unittest import mock

    with warnings.catch_warnings(record=True) as caught, mock.patch.dict(os.environ, env or {}):
        warnings.simplefilter("always")
        with np.errstate(all="warn", under="ignore"):
            code, out, err = station_main(*argv)
    assert code in (0, 1, 2), (argv, code, err)
    assert "Traceback" not in err and "internal error" not in err, (argv, err)
    assert not caught, (argv, [f"{w.category.__name__}: {w.message}" for w in caught])
    # a Python/numpy warning prints "FILE:LINE: RuntimeWarning: ..."; the station's own lines say "station: ..."
    assert not re.search(r"[A-Za-z]*Warning\b", err), (argv, err)
    assert all(ln.startswith("station: warning: ") for ln in err.splitlines() if "warning" in ln.lower()), (argv, err)
    if code == 2:
        lines = err.strip().splitlines()
        assert lines and lines[-1].startswith("station: error: ") and len(lines[-1]) < 2000, (argv, err)
        assert sum(ln.startswith("station: error: ") for ln in lines) == 1, (argv, err)
    return code, out, err


# a command line costs 0.1-0.4 s in process: the fast subset runs a dozen per reader, -m slow runs SLOW
fast_cli = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
long_cli = settings(max_examples=max(SLOW // 3, 12), deadline=None, suppress_health_check=[HealthCheck.too_slow])
FUZZ_SIZES = [pytest.param(fast_cli, id="fast"), pytest.param(long_cli, id="long", marks=pytest.mark.slow)]
JOINTS_UR = "q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad]\n0.1,-1.2,1.4,-1.7,-1.5,0.3\n"


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_model_file_fuzz(runs, tmp_path):
    joints = tmp_path / "j.csv"
    joints.write_text(JOINTS_UR)

    def prop(doc):
        f = tmp_path / "m.yaml"
        f.write_text(_yaml(doc))
        _clean_cli(["model", "show", f])
        _clean_cli(["fk", "--model", f, "--joints", joints])

    runs(given(mutated(MODEL_DOC))(prop))()


# a small URDF: every number and word a file author (or a broken exporter) can get wrong is drawn
URDF = """<?xml version="1.0"?>
<robot name="arm2">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="tool"/>
  <joint name="j1" type="{type1}"><parent link="base"/><child link="l1"/>
    <origin xyz="{xyz1}" rpy="{rpy1}"/><axis xyz="{axis1}"/>
    <limit lower="{lo1}" upper="{hi1}" effort="10" velocity="{v1}"/>
  </joint>
  <joint name="j2" type="{type2}"><parent link="l1"/><child link="l2"/>
    <origin xyz="{xyz2}" rpy="{rpy2}"/><axis xyz="{axis2}"/>
    <limit lower="{lo2}" upper="{hi2}" effort="10" velocity="{v2}"/>
  </joint>
  <joint name="t" type="fixed"><parent link="l2"/><child link="tool"/><origin xyz="{xyz3}" rpy="0 0 0"/></joint>
</robot>
"""
URDF_GOOD = {"type1": "revolute", "type2": "revolute", "xyz1": "0 0 0.1", "rpy1": "0 0 0", "axis1": "0 0 1",
             "lo1": "-3", "hi1": "3", "v1": "2", "xyz2": "0.2 0 0", "rpy2": "0 0 0", "axis2": "0 1 0", "lo2": "-2",
             "hi2": "2", "v2": "2", "xyz3": "0.1 0 0"}
urdf_number = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                        st.sampled_from(["1e308", "-1e308", "1e-320", "0", "-0", "1e400", "nan", "inf", "abc", "",
                                         "0x10", "1_0", "\u0661", "3", "-3", "1e9", "1e-9"]))
urdf_triple = st.one_of(st.lists(urdf_number, min_size=3, max_size=3).map(" ".join),
                        st.lists(urdf_number, min_size=0, max_size=5).map(" ".join),
                        st.sampled_from(["0 0 -1e308", "1e308 0 0", "0 0 0", "nan nan nan", "1 1 1"]))


@st.composite
def urdf_text(draw):
    values = dict(URDF_GOOD)
    for key in draw(st.lists(st.sampled_from(sorted(URDF_GOOD)), min_size=1, max_size=3, unique=True)):
        if key.startswith("type"):
            values[key] = draw(st.sampled_from(["revolute", "prismatic", "continuous", "fixed", "floating", "planar",
                                                "screw", ""]))
        elif key[:-1] in ("xyz", "rpy", "axis"):
            values[key] = draw(urdf_triple)
        else:
            values[key] = draw(urdf_number)
    return URDF.format(**values)


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_urdf_fuzz(runs, tmp_path):
    joints = tmp_path / "j.csv"
    joints.write_text("q1[rad],q2[rad]\n0.1,-0.2\n")

    def prop(text):
        f = tmp_path / "arm.urdf"
        f.write_text(text)
        _clean_cli(["model", "show", f])
        _clean_cli(["fk", "--model", f, "--joints", joints])

    runs(given(urdf_text())(prop))()


@pytest.mark.parametrize("text", [URDF.format(**{**URDF_GOOD, "xyz2": "1e308 0 0"}),
                                  URDF.format(**{**URDF_GOOD, "axis2": "0 0 -1e308"}),
                                  URDF.format(**{**URDF_GOOD, "rpy1": "1e308 0 0"})],
                         ids=["origin-1e308", "axis-minus-1e308", "rpy-1e308"])
def test_cli_urdf_issue_cases(tmp_path, text):
    f = tmp_path / "arm.urdf"
    f.write_text(text)
    code, _, err = _clean_cli(["model", "show", f])
    assert code == 2 and str(f) in err, err


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_cell_file_fuzz(runs, tmp_path):
    """A cell file is read before the robot is opened (the robot here is a serial port that does not exist)."""
    env = {"STATION_HOME": str(tmp_path / "home")}

    def prop(doc):
        f = tmp_path / "cell.yaml"
        f.write_text(_yaml(doc))
        _clean_cli(["run", "zero_offsets", "--robot", "dynamixel:///nonexistent/tty?model=omx", "--serial", "S",
                    "--cell", f], env)

    runs(given(mutated(CELL_DOC))(prop))()


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_world_file_fuzz(runs, tmp_path):
    """``station mock world cell``: the world file read, its models built with the hidden errors, a cell
    written."""
    def prop(doc):
        f = tmp_path / "w.yaml"
        f.write_text(_yaml(doc))
        _clean_cli(["mock", "world", "cell", f, "--out", tmp_path / "cell-out.yaml"])

    runs(given(mutated(_world_doc()))(prop))()


CALIBRATION_DOC = {"format": "station-calibration/1", "units": "SI (m, rad)", "model": "ur5e",
                   "parameters": {"offset.j2": {"value": 0.003, "std": 1e-5, "identifiable": True, "reason": None,
                                                "nominal": 0.0, "kind": "model", "unit": "rad"},
                                  "tcp.z": {"value": 0.1, "std": None, "identifiable": False, "reason": "weak",
                                            "nominal": 0.1, "kind": "model", "unit": "m"}},
                   "residuals": {}, "rank": 1, "n_parameters": 2, "converged": True, "iterations": 3}


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_calibration_file_fuzz(runs, tmp_path):
    joints = tmp_path / "j.csv"
    joints.write_text(JOINTS_UR)

    def prop(doc):
        f = tmp_path / "c.json"
        f.write_text(json.dumps(doc))
        _clean_cli(["fk", "--model", "ur5e", "--joints", joints, "--calibration", f])

    runs(given(mutated(CALIBRATION_DOC))(prop))()


# ---- journals: a real session's journal (zero_offsets on the emulated OMX), one event edited -------------------
JOURNAL = Path(__file__).parents[1] / "data" / "journal_zero_offsets_omx.jsonl"


def _journal_lines() -> list[dict]:
    """The recorded journal, made resumable here: its header names the shipped procedure and limits as they are
    now and a robot port that does not exist (resume stops at opening it, after every journal check)."""
    from station.engine.limits import load_limits
    from station.engine.procedure import load_procedure

    lines = [json.loads(x) for x in JOURNAL.read_text().splitlines()]
    lines[0].update(procedure_sha256=load_procedure("zero_offsets").sha256, procedure_path="zero_offsets.py",
                    limits={**lines[0]["limits"], "path": None, "sha256": load_limits(None).sha256},
                    url="dynamixel:///nonexistent/tty?model=omx&ids=11,12,13,14&contact=200")
    return lines


JOURNAL_LINES = _journal_lines()
EVENT_TYPES = sorted({d["type"] for d in JOURNAL_LINES})


@st.composite
def edited_journal(draw) -> list[dict]:
    lines = copy.deepcopy(JOURNAL_LINES)
    kind = draw(st.sampled_from(EVENT_TYPES))
    i = draw(st.sampled_from([k for k, d in enumerate(lines) if d["type"] == kind]))
    lines[i] = draw(mutated(lines[i]))
    return lines


def _write_journal(folder: Path, lines: list[dict], end: bool) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "journal.jsonl"
    path.write_text("".join(json.dumps(d) + "\n" for d in lines if end or d.get("type") != "end"))
    return path


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_journal_fuzz(runs, tmp_path):
    """``records sync`` (read, project, store) and ``resume`` (header, procedure by name, limits, plan, cell,
    options: all checked before the robot is opened) of a journal with one event edited; the long run also
    rebuilds the report."""
    env = {"STATION_HOME": str(tmp_path / "home")}
    db = f"sqlite:///{tmp_path / 'r.db'}"
    report = runs is long_cli

    def prop(lines):
        done = _write_journal(tmp_path / "done", lines, end=True)
        _clean_cli(["records", "sync", done, "--db", db], env)
        if report:
            _clean_cli(["report", done, "--out", tmp_path / "report"], env)
        folder = tmp_path / "home" / "sessions" / "S-fuzz"
        _write_journal(folder, lines, end=False)
        code, _, err = _clean_cli(["resume", folder, "--db", db], env)
        assert code == 2, err  # the robot is never reached; every journal problem is one line before it

    runs(given(edited_journal())(prop))()


@pytest.mark.parametrize("where, value, says", [
    (("plan", "plan", "poses", 2, "approach_q", 1), "abc", "field plan.poses[2].approach_q"),
    (("plan", "plan", "poses", 1, "q"), [0.1, 0.2], "field plan.poses[1].q: expected 4 joint values, got 2"),
    (("plan", "plan", "poses", 1, "set"), "fit ", "field plan.poses[1].set"),
    (("plan", "plan", "poses", 3, "approach_q", 0), 1e308, "field plan.poses[3].approach_q"),
    (("sample", "measured"), [0.1, 0.2], "field measured: expected [x, y, z]"),
    (("header", "options", "n_holdout"), "4", "field options.n_holdout"),
    (("header", "options", "cone_deg"), 1e308, "field options.cone_deg"),
    (("header", "cell", "points", 0, "position", 2), "abc", "field cell: points[0].position"),
    (("header", "cell", "points", 0, "approach"), [0, 0, 0], "field cell: points[0].approach"),
    (("header", "cell", "points", 0, "radius"), -1, "field cell: points[0].radius"),
])
def test_journal_issue_cases(tmp_path, where, value, says):
    """The issue's journal: ``approach_q`` holding a string (was "ValueError: setting an array element with a
    sequence" after the robot had been opened) and its relatives: one line naming the journal, its line and the
    field, from every command that reads it."""
    lines = copy.deepcopy(JOURNAL_LINES)
    i = next(k for k, d in enumerate(lines) if d["type"] == where[0])
    node = lines[i]
    for k in where[1:-1]:
        node = node[k]
    node[where[-1]] = value
    env = {"STATION_HOME": str(tmp_path / "home")}
    folder = tmp_path / "home" / "sessions" / "S-1"
    path = _write_journal(folder, lines, end=False)
    # what resume alone acts on (the header's cell and options) is checked by resume; the rest by every reader
    readers = [["resume", "S-1"]] + ([] if where[0] == "header" else
                                     [["records", "sync", "S-1", "--db", f"sqlite:///{tmp_path / 'r.db'}"]])
    for argv in readers:
        code, _, err = _clean_cli(argv, env)
        assert code == 2 and f"{path}:{i + 1}: {says}" in err, (argv, err)


# ---- correction maps (station-map/1) ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def map_files(tmp_path_factory):
    """A real map of the planar two-strut robot with hidden errors (plan, 'measure' with the true model, build),
    and a readings and a targets file for ``map correct`` / ``map apply``."""
    d = tmp_path_factory.mktemp("map")
    truth = load_model("struts2").with_params({"strut.1.offset": 2.5e-4, "pivot.2.y": -6e-4})
    assert station_main("map", "plan", "--model", "struts2", "--grid", "2", "--out", d / "plan.csv").code == 0
    rows = [r.split(",") for r in (d / "plan.csv").read_text().splitlines() if r and not r.startswith("#")]
    x = np.array([[float(v) for v in r] for r in rows[1:]])
    xy = truth.fk(x)[:, :2, 3]
    (d / "m.csv").write_text("x1,x2,x,y\n" + "".join(",".join(repr(float(v)) for v in (*a, *b)) + "\n"
                                                     for a, b in zip(x, xy, strict=True)))
    code, _, err = station_main("map", "build", "--model", "struts2", "--samples", d / "m.csv", "--out", d / "map.json")
    assert code == 0, err
    (d / "readings.csv").write_text("x1,x2\n" + "".join(f"{a!r},{b!r}\n" for a, b in x[:3]))
    (d / "targets.csv").write_text("x,y\n" + "".join(f"{a!r},{b!r}\n" for a, b in xy[:3]))
    return d, json.loads((d / "map.json").read_text())


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_map_file_fuzz(runs, map_files, tmp_path):
    d, base = map_files

    def prop(doc):
        f = tmp_path / "map.json"
        f.write_text(json.dumps(doc))
        _clean_cli(["map", "correct", "--model", "struts2", "--map", f, "--joints", d / "readings.csv",
                    "--out", tmp_path / "o.csv"])
        _clean_cli(["map", "apply", "--model", "struts2", "--map", f, "--poses", d / "targets.csv",
                    "--out", tmp_path / "o.csv"])

    runs(given(mutated(base))(prop))()


# ---- robot URLs ---------------------------------------------------------------------------------------------------
URL_SCHEMES = ("ur", "dynamixel", "canopen+virtual", "canopen+socketcand")


@functools.cache
def _url_options() -> dict[str, list[str]]:
    """Each driver's URL option names (imports the drivers: only when a URL is drawn)."""
    from station.robot.registry import driver_class

    return {s: [o.name for o in driver_class(s).options] for s in URL_SCHEMES}
url_value = st.one_of(st.sampled_from(["", "0", "1", "-1", "nan", "inf", "-inf", "1e308", "1e-320", "99999999999",
                                       "1-6", "11,12,14", "6-1", "0-255", "0-300", "omx", "ur5e", "ur10e", "arm6",
                                       "scara", "hexapod", "/etc/passwd", "../x", "%00", "yes", "any", "XM430-W350"]),
                      st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-10**20, 10**20).map(str),
                      st.text(max_size=12))


@st.composite
def robot_urls(draw) -> str:
    from urllib.parse import quote

    scheme = draw(st.sampled_from([*URL_SCHEMES, "UR", "ftp", "canopen", "", "ur+x"]))
    names = _url_options().get(scheme.lower(), ["model"]) + ["bogus"]
    query = [(draw(st.sampled_from(names)), draw(url_value)) for _ in range(draw(st.integers(0, 5)))]
    host = draw(st.sampled_from(["", "127.0.0.1", "[::1]", "[::1", "host:99999", "h:0", "a@b", "ur5", "chan0",
                                 "192.0.2.7:29536", "%41", "\u00e9t\u00e9"]))
    path = draw(st.sampled_from(["", "/", "/dev/nonexistent-tty", "/x/../y", "/" + "a" * 300]))
    q = "&".join(f"{quote(k)}={quote(v, safe='')}" for k, v in query)
    return f"{scheme}://{host}{path}" + (f"?{q}" if q or draw(st.booleans()) else "")


@pytest.mark.parametrize("runs", FUZZ_SIZES)
def test_cli_robot_url_fuzz(runs, tmp_path):
    """``station run --robot URL``: every option parsed, the model loaded and checked against the URL, the
    calibration file a URL may name read, before anything is opened. The drivers' constructors (which open the
    bus) are replaced by one that refuses: no connection is ever attempted, whatever the URL says."""
    from unittest import mock

    from station.robot.errors import DeviceFault
    from station.robot.registry import driver_class

    def refuse(self, *a, **kw):
        raise DeviceFault("the fuzzed URL was accepted up to opening the bus (not opened)")

    env = {"STATION_HOME": str(tmp_path / "home")}

    def prop(url):
        with contextlib.ExitStack() as stack:
            for scheme in URL_SCHEMES:
                stack.enter_context(mock.patch.object(driver_class(scheme), "__init__", refuse))
            code, _, err = _clean_cli(["run", "zero_offsets", "--robot", url, "--serial", "S"], env)
        assert code == 2, err

    runs(given(robot_urls())(prop))()
