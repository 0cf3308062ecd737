"""Regression corpus of the hostile-input campaign: every hostile or careless input it named is one line
``station: error: ...`` and exit 2 (never a traceback, never exit 1, never a hang, never a silent answer).

The CLI runs in-process (``station.cli.main`` with ``sys.argv``) so the corpus stays fast; a handful of cases
run through the installed command to prove the same holds out of process."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from clirunner import station_main, station_proc

from station.kinematics import dump_model, load_model

UR_Q = "q1[rad],q2[rad],q3[rad],q4[rad],q5[rad],q6[rad]\n0.3,-1.2,1.5,-1.9,-1.57,0.4\n"


def assert_one_line(code: int, err: str, *needles: str) -> None:
    lines = err.strip().splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith("station: error: "), err
    assert "Traceback" not in err and "internal error" not in err, err
    for n in needles:
        assert n in lines[0], (n, lines[0])


# ---- model files ---------------------------------------------------------------------------------------------
GOOD_MODEL = """format: station-model/1
name: arm2
convention: dh
units: {length: mm, angle: deg}
joints:
  - limits: [-170, 170]
    dh: {a: 100, alpha: 90, d: 200}
  - limits: [-170, 170]
    dh: {a: 300, alpha: 0, d: 0}
"""

BAD_MODELS = [  # (replace this, with that, expected text in the error)
    ("alpha: 90", "alfa: 90", "unknown key 'alfa'"),
    ("name: arm2", "name: arm2\ntol: {z: 100}", "unknown key 'tol'"),
    ("  - limits: [-170, 170]\n    dh: {a: 100", "  - limits: [-170, 170]\n    offset: true\n    dh: {a: 100",
     "boolean is not a number"),
    ("  - limits: [-170, 170]\n    dh: {a: 100",
     "  - limits: [-170, 170]\n    encoder: {counts_per_rev: 0}\n    dh: {a: 100", "counts_per_rev"),
    ("  - limits: [-170, 170]\n    dh: {a: 100",
     "  - limits: [-170, 170]\n    encoder: {counts_per_rev: 4096, gear: 0}\n    dh: {a: 100", "gear"),
    ("  - limits: [-170, 170]\n    dh: {a: 100",
     "  - limits: [-170, 170]\n    encoder: {counts_per_rev: 4096, direction: 5}\n    dh: {a: 100", "direction"),
    ("  - limits: [-170, 170]\n    dh: {a: 100",
     "  - limits: [-170, 170]\n    encoder: {counts_per_rev: 4096, direction: forward}\n    dh: {a: 100", "direction"),
    ("  - limits: [-170, 170]\n    dh: {a: 100", "  - limits: [-170, 170]\n    encoder: 5\n    dh: {a: 100", "encoder"),
    ("  - limits: [-170, 170]\n    dh: {a: 100",
     "  - limits: [-170, 170]\n    max_velocity: -1\n    dh: {a: 100", "max_velocity"),
    ("units: {length: mm, angle: deg}", "units: mm", "units"),
    ("joints:\n", "joints: [1, 2]\nx:\n", "joints"),
    ("name: arm2", "name: arm2\ntool: 5", "tool"),
    ("name: arm2", "name: arm2\nbase: {z: 1e308}", "base.z"),
    ("d: 200", "d: " + "9" * 400, "digits"),
    ("d: 200", "d: 1_0", "'1_0'"),
    ("d: 200", "d: \u0661", "expected a number"),
    ("a: 300", "a: .nan", "finite"),
    ("name: arm2", "name: arm2\nname: arm3", "duplicate key 'name'"),
    ("name: arm2", "name: &x arm2\ndescription: *x", "alias"),
]


@pytest.mark.parametrize("old,new,needle", BAD_MODELS, ids=[c[2][:20] for c in BAD_MODELS])
def test_bad_model_file(tmp_path, old, new, needle):
    assert old in GOOD_MODEL
    f = tmp_path / "m.yaml"
    f.write_text(GOOD_MODEL.replace(old, new, 1))
    code, _, err = station_main("model", "show", f)
    assert_one_line(code, err, needle, str(f))


def test_good_model_file_still_reads(tmp_path):
    f = tmp_path / "m.yaml"
    f.write_text(GOOD_MODEL)
    code, out, err = station_main("model", "show", f)
    assert code == 0, err
    assert "arm2" in out


def test_model_error_names_the_line(tmp_path):
    f = tmp_path / "m.yaml"
    f.write_text(GOOD_MODEL.replace("alpha: 0", "alfa: 0"))
    code, _, err = station_main("model", "show", f)
    assert_one_line(code, err, f"{f}:9: joints[1].dh", "'alfa'")


def test_poe_screw_shapes(tmp_path):
    doc = dump_model(load_model("ur5e").with_params({}), "mm", "deg")
    assert "convention: dh" in doc  # the built-in UR is DH; write a tiny PoE model instead
    poe = ("format: station-model/1\nconvention: poe\nunits: {length: m, angle: rad}\nhome: {x: 1}\n"
           "joints:\n  - limits: [-3, 3]\n    screw: {axis: 5, point: [0, 1]}\n")
    f = tmp_path / "p.yaml"
    f.write_text(poe)
    code, _, err = station_main("model", "show", f)
    assert_one_line(code, err, "screw.axis")
    f.write_text(poe.replace("axis: 5", "axis: [0, 0, 1]"))
    code, _, err = station_main("model", "show", f)
    assert_one_line(code, err, "screw.point")


BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True))


@pytest.mark.parametrize("data", [
    b"\xff\xfef\x00o\x00r\x00m\x00a\x00t\x00", b"format: station-model/1\n\x89PNG\r\n\x1a\n\x00\x00",
    b"format: \xe9\n", ("[" * 30000).encode(), BOMB.encode(), b"description: " + BOMB.replace("\n", " ").encode(),
], ids=["utf16", "binary", "latin1", "deep", "bomb", "bomb-in-field"])
def test_unreadable_yaml(tmp_path, data):
    f = tmp_path / "m.yaml"
    f.write_bytes(data)
    code, _, err = station_main("model", "show", f)
    assert_one_line(code, err, str(f))


@pytest.mark.parametrize("path", ["/dev/zero", "fifo", "dir"])
def test_special_files_are_refused_without_reading(tmp_path, path):
    if path == "fifo":
        path = tmp_path / "f.yaml"
        os.mkfifo(path)
    elif path == "dir":
        path = tmp_path / "d.yaml"
        path.mkdir()
    code, _, err = station_main("model", "show", path)
    assert_one_line(code, err, "not a regular file")


# ---- cell and limits files -----------------------------------------------------------------------------------
CELL = ("format: station-cell/1\nunits: {length: mm, angle: deg}\npoints:\n"
        "  - {label: A, kind: socket, position: [450, 0, 50]}\n")


@pytest.mark.parametrize("text,needle", [
    (CELL + "  - {label: A, kind: socket, position: [0, 450, 50]}\n", "used twice"),
    (CELL.replace("label: A", "label: null"), "label"),
    (CELL.replace("50]}", "50], radius: true}"), "radius"),
    (CELL.replace("points:\n  - {label: A, kind: socket, position: [450, 0, 50]}", "points: {A: 5}"), "points.A"),
    (CELL.replace("label: A", "label: &l A") + "  - {label: *l, position: [1, 2, 3]}\n", "alias"),
    (CELL + "colour: red\n", "unknown key 'colour'"),
])
def test_bad_cell_file(tmp_path, text, needle):
    from station.engine.cell import CellError, load_cell

    f = tmp_path / "cell.yaml"
    f.write_text(text)
    with pytest.raises(CellError, match=None) as e:
        load_cell(f)
    assert needle in str(e.value) and str(f) in str(e.value) and "\n" not in str(e.value)


LIMITS = ("format: station-limits/1\nversion: '1'\nmodels:\n  '*':\n    zero_offsets:\n"
          "      fit_rms: {high: 0.1, unit: mm}\n")


@pytest.mark.parametrize("text,needle", [
    (LIMITS.replace("unit: mm", "unit: m"), "unit slip"),
    (LIMITS.replace("version: '1'", "version: &v '1'\nx: *v"), "alias"),
    (LIMITS.replace("high: 0.1", "high: true"), "True"),
    (LIMITS.replace("high: 0.1", "hihg: 0.1"), "hihg"),
    (LIMITS + "models: {}\n", "duplicate key 'models'"),
])
def test_bad_limits_file(tmp_path, text, needle):
    from station.engine.limits import LimitsError, load_limits

    f = tmp_path / "limits.yaml"
    f.write_text(text)
    with pytest.raises(LimitsError) as e:
        load_limits(f)
    assert needle in str(e.value) and "\n" not in str(e.value)


# ---- samples and joint files, solve and fk -------------------------------------------------------------------
def _samples(tmp_path, rows: np.ndarray, units="rad") -> Path:
    f = tmp_path / "s.csv"
    head = ",".join(f"q{j + 1}[{units}]" for j in range(6))
    f.write_text(head + "\n" + "\n".join(",".join(f"{v:.9g}" for v in r) for r in rows) + "\n")
    return f


def _ur_rows(n=20, seed=1):
    rng = np.random.default_rng(seed)
    return np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4]) + rng.uniform(-0.3, 0.3, (n, 6))


def test_degrees_in_a_radian_column_are_named_per_row(tmp_path):
    rows = _ur_rows()
    rows[6, 2] = 85.0  # this row was written in degrees
    f = _samples(tmp_path, rows)
    code, _, err = station_main("solve", "--model", "ur5e", "--samples", f)
    assert_one_line(code, err, "row 7: q3 = 85 rad is outside the joint limits", "degrees in a radian column?")


def test_all_degrees_under_rad_header(tmp_path):
    f = _samples(tmp_path, np.degrees(_ur_rows()))
    code, _, err = station_main("fk", "--model", "ur5e", "--joints", f)
    assert_one_line(code, err, "outside the joint limits")


@pytest.mark.parametrize("cell", ["1_0", "\u0661", "0x10", "1e400", "nan"])
def test_sample_numbers_must_be_plain(tmp_path, cell):
    f = tmp_path / "s.csv"
    f.write_text(UR_Q.replace("0.3,", f"{cell},"))
    code, _, err = station_main("fk", "--model", "ur5e", "--joints", f)
    assert_one_line(code, err, "q1")


def test_csv_field_beyond_the_csv_limit(tmp_path):
    f = tmp_path / "s.csv"
    f.write_text(UR_Q + '"' + "x" * 140_000 + '",1,2,3,4,5\n')
    code, _, err = station_main("fk", "--model", "ur5e", "--joints", f)
    assert_one_line(code, err, "not a CSV row")


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_max_std_must_be_positive_and_finite(tmp_path, value):
    f = _samples(tmp_path, _ur_rows())
    code, _, err = station_main("solve", "--model", "ur5e", "--samples", f, f"--max-std={value}")
    assert_one_line(code, err, "--max-std")


@pytest.mark.parametrize("args,needle", [
    (["--identify", ""], "--identify"),
    (["--identify", "offsets,,tcp"], "--identify"),
    (["--reference", "A=0,0,0", "--reference", "A=1,1,1mm"], "twice"),
])
def test_solve_options(tmp_path, args, needle):
    f = _samples(tmp_path, _ur_rows())
    code, _, err = station_main("solve", "--model", "ur5e", "--samples", f, *args)
    assert_one_line(code, err, needle)


def test_out_equal_to_samples_is_refused_and_samples_kept(tmp_path):
    f = _samples(tmp_path, _ur_rows())
    before = f.read_bytes()
    code, _, err = station_main("solve", "--model", "ur5e", "--samples", f, "--out", f)
    assert_one_line(code, err, "refusing to overwrite")
    assert f.read_bytes() == before


@pytest.mark.parametrize("where", ["dir", "missing", "readonly"])
def test_unwritable_out_is_one_line_and_leaves_nothing(tmp_path, where):
    f = tmp_path / "j.csv"
    f.write_text(UR_Q)
    if where == "dir":
        out = tmp_path / "adir"
        out.mkdir()
    elif where == "missing":
        out = tmp_path / "nope" / "x.csv"
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        out = ro / "x.csv"
        if os.access(ro, os.W_OK):  # root (CI) ignores permissions: a folder that is a file refuses even root
            (tmp_path / "afile").write_text("")
            out = tmp_path / "afile" / "x.csv"
    code, _, err = station_main("fk", "--model", "ur5e", "--joints", f, "--out", out)
    assert_one_line(code, err, "--out")
    assert not list(tmp_path.rglob("*.tmp"))


def _result(tmp_path) -> dict:
    """A real calibration result: solve on samples simulated from a ground-truth UR5e."""
    from station.solver.simulate import touch_observations

    truth = load_model("ur5e").with_params({"tcp.z": 0.1, "offset.j2": 0.003})
    q0 = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
    obs = touch_observations(truth, {"A": truth.position(q0)}, 30, np.random.default_rng(3), centre=q0, spread=0.3)
    f = _samples(tmp_path, obs.q)
    out = tmp_path / "r.json"
    p = station_proc("solve", "--model", "ur5e", "--samples", f, "--tool", "0,0,0.1", "--out", out)
    assert p.code == 0, p.err
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    return _result(tmp_path_factory.mktemp("res"))


def test_result_json_is_strict_json(result):
    text = json.dumps(result)
    json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in result JSON"))
    assert result["format"] == "station-calibration/1"


@pytest.mark.parametrize("change,needle", [
    (lambda d: d["parameters"].__setitem__("offset.j2", {**d["parameters"]["offset.j2"], "value": "NaN"}),
     "not JSON"),
    (lambda d: d["parameters"].__setitem__("offset.j2", {**d["parameters"]["offset.j2"], "value": "Infinity"}),
     "not JSON"),
    (lambda d: d["parameters"].__setitem__("offset.j2", {**d["parameters"]["offset.j2"], "value": None}), "null"),
    (lambda d: d.__setitem__("parameters", []), "parameters"),
    (lambda d: d.__setitem__("format", "station-calibration/9"), "format"),
    (lambda d: d.__setitem__("units", "mm"), "units"),
    (lambda d: d["parameters"].__setitem__("offset.j2", {**d["parameters"]["offset.j2"], "value": True}),
     "boolean"),
    (lambda d: d.__setitem__("notes", "[" * 100_000), "nested"),
])
def test_bad_calibration_json(tmp_path, result, change, needle):
    doc = json.loads(json.dumps(result))
    change(doc)
    text = json.dumps(doc)
    text = text.replace('"NaN"', "NaN").replace('"Infinity"', "Infinity")
    if needle == "nested":
        text = text.replace('"' + "[" * 100_000 + '"', "[" * 100_000 + "]" * 100_000)
    cal = tmp_path / "c.json"
    cal.write_text(text)
    j = tmp_path / "j.csv"
    j.write_text(UR_Q)
    code, _, err = station_main("fk", "--model", "ur5e", "--tool", "0,0,0.1", "--calibration", cal, "--joints", j)
    assert_one_line(code, err, needle)


def test_calibration_directory(tmp_path):
    j = tmp_path / "j.csv"
    j.write_text(UR_Q)
    code, _, err = station_main("fk", "--model", "ur5e", "--calibration", tmp_path, "--joints", j)
    assert_one_line(code, err, "directory")


def test_good_calibration_applies(tmp_path, result):
    cal = tmp_path / "c.json"
    cal.write_text(json.dumps(result))
    j = tmp_path / "j.csv"
    j.write_text(UR_Q)
    code, out, err = station_main("fk", "--model", "ur5e", "--tool", "0,0,0.1", "--calibration", cal, "--joints", j)
    assert code == 0, err
    assert "calibration" in out


# ---- run options: refused before any robot is opened (the URL points at nothing) ----------------------------
NOBODY = "ur://127.0.0.250"


@pytest.mark.parametrize("args,needle", [
    (["--poses", "0"], "--poses"), (["--poses", "-5"], "--poses"), (["--holdout", "-1"], "--holdout"),
    (["--cone", "-10"], "--cone"), (["--cone", "0"], "--cone"), (["--cone", "180"], "--cone"),
    (["--cone", "nan"], "--cone"), (["--seed", "-1"], "--seed"), (["--touch", "bogus"], "--touch"),
])
def test_run_options_checked_before_connecting(args, needle):
    code, _, err = station_main("run", "zero_offsets", "--robot", NOBODY, "--serial", "S", *args)
    assert_one_line(code, err, needle)


def test_run_limits_unit_slip_before_connecting(tmp_path):
    f = tmp_path / "l.yaml"
    f.write_text(LIMITS.replace("unit: mm", "unit: m"))
    code, _, err = station_main("run", "zero_offsets", "--robot", NOBODY, "--serial", "S", "--limits", f)
    assert_one_line(code, err, "unit slip")


@pytest.mark.parametrize("url,needle", [
    ("ur://[::1?x", "not a URL"), ("dynamixel:///dev/null?ids=1-100000000&model=omx", "id"),
])
def test_urls(url, needle):
    code, _, err = station_main("run", "zero_offsets", "--robot", url, "--serial", "S")
    assert_one_line(code, err, needle)


# ---- a crash is exit 2, never the FAIL code -----------------------------------------------------------------
def test_internal_error_is_exit_2_one_line(tmp_path):
    """A bug (here: a command that raises ZeroDivisionError) is reported as an internal error, exit 2."""
    boom = "from station import cli\n@cli.app.command('boom')\ndef boom():\n    1 / 0\n"
    env = {k: v for k, v in os.environ.items() if k != "STATION_DEBUG"}
    p = station_proc("boom", prelude=boom, timeout=60, env=env, replace_env=True)
    assert p.code == 2
    lines = p.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: internal error: ZeroDivisionError"), p.err
    p = station_proc("boom", prelude=boom, timeout=60, env=env | {"STATION_DEBUG": "1"}, replace_env=True)
    assert p.code == 2 and "Traceback" in p.err


def test_out_of_process_fifo_does_not_hang(tmp_path):
    fifo = tmp_path / "cell.yaml"
    os.mkfifo(fifo)
    p = station_proc("run", "zero_offsets", "--robot", NOBODY, "--serial", "S", "--cell", fifo, timeout=60)
    assert p.code == 2 and "FIFO" in p.err and len(p.err_lines) == 1, p.err


# ---- bounded cost --------------------------------------------------------------------------------------------
def test_report_widest_tool_axes_without_an_n_by_n_matrix():
    """The report's widest pair of tool axes: same as the full N x N comparison on 3000 axes; on 100k axes the
    peak memory stays far below the 80 GB an N x N matrix would take."""
    import tracemalloc

    from station.report.analysis import _min_pairwise_dot

    rng = np.random.default_rng(4)
    z = rng.normal([0, 0, -1], 0.3, (3000, 3))
    z /= np.linalg.norm(z, axis=1)[:, None]
    assert _min_pairwise_dot(z) == pytest.approx(float((z @ z.T).min()), abs=1e-12)
    z = rng.normal([0, 0, -1], 0.3, (100_000, 3))
    z /= np.linalg.norm(z, axis=1)[:, None]
    tracemalloc.start()
    d = _min_pairwise_dot(z)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 300e6 and -1 <= d < -0.99
