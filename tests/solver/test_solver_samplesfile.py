"""Samples CSV: units in headers, one-line errors naming file, line and column; mm/deg input gives the
same calibration as m/rad."""

import numpy as np
import pytest

from station.kinematics import load_model
from station.samplesfile import SamplesFileError, read_joints, read_samples
from station.solver import Observations, solve
from station.solver.simulate import touch_observations


def write_csv(path, q, labels, kinds, units=("rad", "m"), measured=None, munit="m"):
    ang, lin = units
    fa = 1.0 if ang == "rad" else 180 / np.pi
    fl = {"m": 1.0, "mm": 1e3}[lin]
    head = [f"q{j + 1}[{ang if k == 'revolute' else lin}]" for j, k in enumerate(kinds)] + ["point"]
    if measured is not None:
        head += [f"{a}[{munit}]" for a in "xyz"]
    lines = ["# touch samples", ",".join(head)]
    for i, row in enumerate(q):
        vals = [f"{v * (fa if k == 'revolute' else fl):.12g}" for v, k in zip(row, kinds, strict=True)] + [labels[i]]
        if measured is not None:
            vals += [f"{v * {'m': 1.0, 'mm': 1e3}[munit]:.12g}" for v in measured[i]]
        lines.append(",".join(vals))
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def scara_data():
    nominal = load_model("scara").with_params({"tcp.x": 0.02})
    truth = nominal.with_params({"offset.j1": 0.004, "offset.j2": -0.003, "offset.j3": 0.0011})
    rng = np.random.default_rng(7)
    mid = (nominal.lower + nominal.upper) / 2
    pts = {"A": truth.position(mid + [0.4, 0.5, 0.05, 0.0]), "B": truth.position(mid + [-0.5, 0.6, 0.1, 0.0])}
    return nominal, touch_observations(truth, pts, 15, rng, centre=mid, spread=0.9), pts


def test_mm_deg_file_gives_the_same_answer_as_m_rad(tmp_path, scara_data):
    nominal, obs, pts = scara_data
    kinds = [j.kind for j in nominal.joints]
    write_csv(tmp_path / "si.csv", obs.q, obs.point, kinds)
    write_csv(tmp_path / "mmdeg.csv", obs.q, obs.point, kinds, ("deg", "mm"))
    a, b = read_samples(tmp_path / "si.csv", nominal), read_samples(tmp_path / "mmdeg.csv", nominal)
    np.testing.assert_allclose(a.q, obs.q, atol=1e-12)
    np.testing.assert_allclose(b.q, obs.q, atol=1e-10)
    assert list(b.point) == list(obs.point)
    spec = "offset.j1,offset.j2,offset.j3,tcp.x,tcp.y"
    ra = solve(nominal, Observations(a.q, a.point), spec, pts)
    rb = solve(nominal, Observations(b.q, b.point), spec, pts)
    for n in ra.identified:
        assert rb.parameters[n].value == pytest.approx(ra.parameters[n].value, abs=1e-9)
        assert rb.parameters[n].std == pytest.approx(ra.parameters[n].std, rel=1e-4)


def test_measured_columns_in_mm(tmp_path):
    m = load_model("ur5e")
    q = np.random.default_rng(1).uniform(-1, 1, (5, 6))
    P = m.position(q)
    write_csv(tmp_path / "m.csv", q, ["A"] * 5, [j.kind for j in m.joints], measured=P, munit="mm")
    s = read_samples(tmp_path / "m.csv", m)
    np.testing.assert_allclose(s.measured, P, atol=1e-12)
    assert s.lines == [3, 4, 5, 6, 7]


@pytest.mark.parametrize("text, message", [
    ("q1,q2,q3,q4,q5\n1,2,3,4,5\n", "bad.csv: missing column 'q6'"),
    ("q1,q2,q3,q4,q5,q6,q7\n" + "0," * 6 + "0\n", "bad.csv: wrong joint count"),
    ("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n0,0,abc,0,0,0\n", "bad.csv:3: column 'q3': not a number ('abc')"),
    ("# c\nq1,q2,q3,q4,q5,q6\n0,0,nan,0,0,0\n", "bad.csv:3: column 'q3': not a finite number"),
    ("q1[mm],q2,q3,q4,q5,q6\n0,0,0,0,0,0\n", "bad.csv:1: column 'q1[mm]': joint 1 is revolute"),
    ("q1[furlong],q2,q3,q4,q5,q6\n0,0,0,0,0,0\n", "unknown unit 'furlong'"),
    ("q1,q2,q3,q4,q5,q6,x,y\n" + "0," * 7 + "0\n", "missing column 'z'"),
    ("q1,q2,q3,q4,q5,q6\n0,0,0\n", "bad.csv:2: 3 fields, the header has 6"),
    ("q1,q2,q3,q4,q5,q6,point\n0,0,0,0,0,0,\n", "bad.csv:2: column 'point': empty label"),
    ("", "bad.csv: empty file"),
    ("q1,q2,q3,q4,q5,q6\n", "bad.csv: no data rows"),
])
def test_errors_name_file_line_and_column(tmp_path, text, message):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(SamplesFileError) as e:
        read_samples(p, load_model("ur5e"))
    assert message in str(e.value).replace(str(tmp_path) + "/", "")
    assert "\n" not in str(e.value)


def test_prismatic_joint_rejects_angle_unit(tmp_path):
    p = tmp_path / "j.csv"
    p.write_text("q1,q2,q3[deg],q4\n0,0,0,0\n")
    with pytest.raises(SamplesFileError, match="joint 3 is prismatic"):
        read_joints(p, load_model("scara"))
    p.write_text("q1[deg],q2[deg],q3[mm],q4[deg]\n90,0,100,0\n")
    q, _ = read_joints(p, load_model("scara"))
    np.testing.assert_allclose(q, [[np.pi / 2, 0, 0.1, 0]])


def test_readings_beyond_the_limits_are_data_with_one_warning_per_joint(tmp_path):
    """A real recording (MUKCa, Kinova Gen3 lite: joint 6 read 2.43 rad with the URDF's limits +-2.09) is used as
    recorded; the warning names the joint, how many readings and how far. Degrees stay refused where they fit."""
    from pathlib import Path

    from clirunner import station_proc

    data = Path(__file__).parents[1] / "data" / "mukca"
    m = load_model(data / "gen3lite.urdf", tip_link="ball_link")
    rows = []
    for h, lab in ((0, "A"), (1, "B")):
        rows += [ln.strip() + f",{lab}" for ln in (data / "dinova_2" / "front" / f"hole_{h}.csv").read_text().split()]
    f = tmp_path / "s.csv"
    f.write_text("q1,q2,q3,q4,q5,q6,point\n" + "\n".join(rows) + "\n")
    s = read_samples(f, m)
    assert len(s.q) == len(rows) and np.abs(s.q[:, 5]).max() > 2.09 + np.radians(5)
    (w,) = s.warnings
    assert w.startswith(f"{f}: q6 (joint_6): ") and "beyond the joint limits [-2.09, 2.09] rad, by up to" in w
    r = station_proc("fk", "--model", data / "gen3lite.urdf", "--tip-link", "ball_link", "--joints", f, timeout=60)
    assert r.code == 0 and r.err.startswith("station: warning: ") and len(r.err.splitlines()) == 1
    q = s.q.copy()
    q[:, 2] = np.degrees(q[:, 2])  # a column in degrees under a radian header: still a unit slip, refused
    f.write_text("q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(f"{v:.9g}" for v in r_) for r_ in q) + "\n")
    with pytest.raises(SamplesFileError, match="degrees in a radian column"):
        read_joints(f, m)
