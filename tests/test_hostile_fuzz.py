"""Property-based fuzzing (hypothesis) of every reader and of the CLI entry points (issue 14): whatever the
input — random bytes, random structure, random numbers incl. NaN/inf/huge, random units — the result is a
valid value or the reader's own one-line error; the CLI exits 0 with a valid result or 2 with one line; never
a traceback, never another exception, never a hang (pytest-timeout bounds each test).

The fast subset runs ``FAST`` examples per property; ``-m slow`` runs ``SLOW`` (set HYPOTHESIS_SLOW_EXAMPLES)."""

import copy
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
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
def _cli(argv):
    """``station ARGV`` in process: (exit code, stdout, stderr)."""
    import contextlib
    import io
    import sys

    from station.cli import main

    out, err = io.StringIO(), io.StringIO()
    old = sys.argv
    sys.argv = ["station", *map(str, argv)]
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    finally:
        sys.argv = old
    return code, out.getvalue(), err.getvalue()


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
        code, out, err = _cli(["fk", "--model", "ur5e", "--joints", f])
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
        code, _, err = _cli(["run", "zero_offsets", "--robot", "ur://127.0.0.250", "--serial", "S", option, value])
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
