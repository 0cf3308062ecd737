"""``station map plan|build|apply|correct`` end to end: files written the way an instrument or a user writes them,
the true robot from the simulated world, mm/deg headers giving the SI answer, one-line errors with exit 2."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from clirunner import station_main, station_proc
from station.mocks.world import World

from station.kinematics import se3

FULL = ("x", "y", "z", "rx", "ry", "rz")


def read_csv(path):
    """Header and values of the result columns (apply/correct: those before ``status``, every row ok)."""
    lines = [ln for ln in Path(path).read_text().splitlines() if ln and not ln.startswith("#")]
    head = lines[0].split(",")
    k = head.index("status") if "status" in head else len(head)
    rows = [ln.split(",") for ln in lines[1:]]
    assert all(r[k] == "ok" for r in rows) if k < len(head) else True, lines
    return head[:k], np.array([[float(v) for v in r[:k]] for r in rows])


def write_csv(path, header, rows):
    Path(path).write_text(",".join(header) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")


def measured_file(path, x, T, planar, mm=False):
    """What an instrument delivers: actuator values and the measured pose (base frame)."""
    n = x.shape[1]
    if planar:
        pose, cols = T[:, :2, 3], ["x", "y"]
    else:
        pose, cols = se3.matrix_to_pose(T, "rotvec"), list(FULL)
    if mm:
        k = np.array([1e3] * n + [1e3 if not c.startswith("r") else 180 / np.pi for c in cols])
        header = [f"x{i + 1}[mm]" for i in range(n)] + [f"{c}[{'deg' if c.startswith('r') else 'mm'}]" for c in cols]
    else:
        k = np.ones(n + len(cols))
        header = [f"x{i + 1}" for i in range(n)] + cols
    write_csv(path, header, np.hstack([x, pose]) * k)


def ok(*args):
    rc, out, err = station_main(*args)
    assert rc == 0, err
    return out


def one_line_error(*args, contains=()):
    r = station_main(*args)
    rc, lines = r.code, r.err_lines
    assert rc == 2, lines
    assert len(lines) == 1 and lines[0].startswith("station: error:"), lines
    for c in contains:
        assert c in lines[0], lines
    return lines[0]


@pytest.fixture(scope="module")
def struts(tmp_path_factory):
    d = tmp_path_factory.mktemp("struts")
    w = World.from_dict({"format": "station-world/1", "units": {"length": "mm", "angle": "deg"},
                         "robot": {"model": "struts2"},
                         "errors": {"explicit": {"pivot.1.x": 0.4, "pivot.2.y": -0.6, "strut.1.offset": 0.25,
                                                 "strut.2.offset": -0.3}}})
    ok("map", "plan", "--model", "struts2", "--grid", "2", "--out", d / "plan.csv")
    header, x = read_csv(d / "plan.csv")
    assert header == ["x1", "x2"] and len(x) == 9
    T = w.truth.fk(x)
    measured_file(d / "m_si.csv", x, T, planar=True)
    measured_file(d / "m_mm.csv", x, T, planar=True, mm=True)
    return d, w


def test_struts_round_trip_and_units(struts):
    d, w = struts
    out = ok("map", "build", "--model", "struts2", "--samples", d / "m_si.csv", "--grid", "2", "--out", d / "si.json")
    assert "9 samples on 9 of 9 grid nodes" in out and "us per query" in out
    ok("map", "build", "--model", "struts2", "--samples", d / "m_mm.csv", "--out", d / "mm.json")
    a, b = (json.loads((d / f).read_text()) for f in ("si.json", "mm.json"))
    np.testing.assert_allclose(a["nodes"]["summand"], b["nodes"]["summand"], atol=1e-12)
    # calibrated control: held-out targets reached by the true robot
    rng = np.random.default_rng(3)
    xt = 0.31 + 0.18 * rng.uniform(0, 1, (30, 2))
    targets = w.truth.fk(xt)[:, :2, 3]
    write_csv(d / "t_si.csv", ["x", "y"], targets)
    write_csv(d / "t_mm.csv", ["y[mm]", "x[mm]"], targets[:, ::-1] * 1e3)  # column order is free
    ok("map", "apply", "--model", "struts2", "--map", d / "si.json", "--poses", d / "t_si.csv", "--out", d / "c1.csv")
    ok("map", "apply", "--model", "struts2", "--map", d / "mm.json", "--poses", d / "t_mm.csv", "--out", d / "c2.csv",
       "--units", "mm,deg")
    h1, c1 = read_csv(d / "c1.csv")
    h2, c2 = read_csv(d / "c2.csv")
    assert h1 == ["x1", "x2"] and h2 == ["x1[mm]", "x2[mm]"]
    np.testing.assert_allclose(c2 / 1e3, c1, atol=1e-12)
    nominal = w.nominal.ik_closed(targets)[0]
    before = np.linalg.norm(w.truth.fk(nominal)[:, :2, 3] - targets, axis=1)
    after = np.linalg.norm(w.truth.fk(c1)[:, :2, 3] - targets, axis=1)
    assert np.sqrt(np.mean(after ** 2)) < 0.03 * np.sqrt(np.mean(before ** 2))
    # measuring kinematics: readings in, corrected poses out; the true hinge position is recovered
    write_csv(d / "r.csv", ["x1", "x2"], xt)
    write_csv(d / "r_mm.csv", ["x1[mm]", "x2[mm]"], xt * 1e3)
    ok("map", "correct", "--model", "struts2", "--map", d / "si.json", "--joints", d / "r.csv", "--out", d / "p1.csv")
    ok("map", "correct", "--model", "struts2", "--map", d / "si.json", "--joints", d / "r_mm.csv", "--out",
       d / "p2.csv", "--units", "mm,deg")
    h1, p1 = read_csv(d / "p1.csv")
    h2, p2 = read_csv(d / "p2.csv")
    assert h1 == ["x", "y"] and h2 == ["x[mm]", "y[mm]"]
    np.testing.assert_allclose(p2 / 1e3, p1, atol=1e-12)
    err_nominal = np.linalg.norm(w.nominal.fk(xt)[:, :2, 3] - targets, axis=1)
    err_map = np.linalg.norm(p1 - targets, axis=1)
    assert np.sqrt(np.mean(err_map ** 2)) < 0.03 * np.sqrt(np.mean(err_nominal ** 2))


@pytest.mark.parametrize("content,command,contains", [
    ("x1[deg],x2\n0.4,0.4\n", "correct", ["'x1[deg]'", "must be a length"]),
    ("q1,q2\n0.4,0.4\n", "correct", ["missing column 'x1'"]),
    ("x1,x2,x3\n0.4,0.4,0.1\n", "correct", ["wrong columns: x3", "2 actuators"]),
    ("x1,x2\n0.4,abc\n", "correct", ["r.csv:2", "not a number"]),
    ("x,y,z\n0.2,0.3,0\n", "apply", ["needs pose columns x,y"]),
])
def test_bad_input_is_one_line_exit_2(struts, content, command, contains):
    d, _ = struts
    if not (d / "si.json").exists():
        ok("map", "build", "--model", "struts2", "--samples", d / "m_si.csv", "--out", d / "si.json")
    f = d / "r.csv"
    f.write_text(content)
    flag = "--joints" if command == "correct" else "--poses"
    one_line_error("map", command, "--model", "struts2", "--map", d / "si.json", flag, f, "--out", d / "o.csv",
                   contains=contains)


def test_apply_and_correct_answer_every_row(struts):
    """A target or reading the map cannot serve gets a status naming why, every other row its command or pose
    (the same as alone), the input's columns and comments are kept, and the command exits 1 naming how many."""
    d, w = struts
    if not (d / "si.json").exists():
        ok("map", "build", "--model", "struts2", "--samples", d / "m_si.csv", "--out", d / "si.json")
    good = [[0.2, 0.35], [0.25, 0.4]]
    bad = {"5,5": "unreachable", "0.2,-0.3": "other side of the pivot line",
           "0.0,0.5": "unreachable: its inverse kinematics gives x2",
           "0.31875,0.391693": "unreachable: x1 0.5045 m above 0.5 m"}  # strut 1 at 505 mm
    f = d / "mixed.csv"
    rows = [("A", *good[0]), ("B", "5", "5"), ("C", "0.2", "-0.3"), ("D", *good[1]), ("E", "0.0", "0.5"),
            ("F", "0.31875", "0.391693")]
    f.write_text("# targets of line 3\nlabel,x,y\n" + "".join(f"{a},{b},{c}\n" for a, b, c in rows))
    r = station_main("map", "apply", "--model", "struts2", "--map", d / "si.json", "--poses", f, "--out",
                     d / "mixed_out.csv")
    rc, err = r.code, r.err_lines
    assert rc == 1, err
    assert err[0].startswith("station: 4 of 6 targets have no command"), err
    text = (d / "mixed_out.csv").read_text().splitlines()
    assert text[0] == "# targets of line 3" and text[1] == "x1,x2,status,label,x,y"
    cells = list(csv.reader(text[2:]))
    assert [c[3] for c in cells] == list("ABCDEF") and [c[4:] for c in cells] == [[str(a), str(b)] for _, a, b in rows]
    for c in cells:
        key = f"{c[4]},{c[5]}"
        if key in bad:
            assert c[0] == c[1] == "" and bad[key] in c[2], c
        else:
            assert c[2] == "ok" and c[0] and c[1], c
    # the served rows are what they are alone
    alone = d / "good.csv"
    write_csv(alone, ["x", "y"], good)
    ok("map", "apply", "--model", "struts2", "--map", d / "si.json", "--poses", alone, "--out", d / "good_out.csv")
    _, c_alone = read_csv(d / "good_out.csv")
    served = np.array([[float(v) for v in c[:2]] for c in cells if c[2] == "ok"])
    np.testing.assert_allclose(served, c_alone, atol=1e-12)
    # correct: a reading outside the map gets its status; exit 1
    (d / "readings.csv").write_text("x1,x2\n0.4,0.4\n400,400\n")
    r = station_main("map", "correct", "--model", "struts2", "--map", d / "si.json", "--joints",
                     d / "readings.csv", "--out", d / "poses_out.csv")
    rc, err = r.code, r.err_lines
    assert rc == 1 and "1 of 2 readings have no pose" in err[0], err
    lines = list(csv.reader((d / "poses_out.csv").read_text().splitlines()))
    assert lines[0] == ["x", "y", "status", "x1", "x2"] and lines[1][2] == "ok"
    assert lines[2][:2] == ["", ""] and "outside the map" in lines[2][2] and lines[2][3:] == ["400", "400"], lines


def test_bad_maps_samples_and_options_are_one_line(struts, tmp_path):
    d, w = struts
    one_line_error("map", "plan", "--model", "struts2", "--grid", "1", "--exclude-ends", "--out", tmp_path / "p.csv",
                   contains=["at least 2"])
    one_line_error("map", "plan", "--model", "struts2", "--grid", "2,2,2", "--out", tmp_path / "p.csv",
                   contains=["one Q or 2"])
    one_line_error("map", "plan", "--model", "struts2", "--grid", "2", "--mesh", "delaunay", "--out",
                   tmp_path / "p.csv", contains=["--mesh"])
    one_line_error("map", "build", "--model", "hexapod", "--samples", d / "m_si.csv", "--out", tmp_path / "m.json",
                   contains=["missing column 'x3'"])
    bad = tmp_path / "m.csv"
    bad.write_text("x1,x2,x,y,rz\n0.3,0.3,0.2,0.2,0\n")
    one_line_error("map", "build", "--model", "struts2", "--samples", bad, "--out", tmp_path / "m.json",
                   contains=["missing column 'rx'"])
    bad.write_text(d.joinpath("m_si.csv").read_text().replace("\n0.3,0.4,", "\n0.3,0.43,", 1))
    one_line_error("map", "build", "--model", "struts2", "--samples", bad, "--grid", "2", "--out", tmp_path / "m.json",
                   contains=["m.csv:3", "not on the grid"])
    (tmp_path / "broken.json").write_text("{\n")
    one_line_error("map", "correct", "--model", "struts2", "--map", tmp_path / "broken.json", "--joints",
                   d / "m_si.csv", "--out", tmp_path / "o.csv", contains=["broken.json", "not valid JSON"])
    (tmp_path / "inf.json").write_text(json.dumps({"format": float("inf")}))  # Python's json writes Infinity
    one_line_error("map", "correct", "--model", "struts2", "--map", tmp_path / "inf.json", "--joints",
                   d / "m_si.csv", "--out", tmp_path / "o.csv", contains=["inf.json", "Infinity is not JSON"])
    doc = json.loads((d / "si.json").read_text())
    doc["mesh"]["levels"][0] = [0.5, 0.3, 0.4]
    (tmp_path / "levels.json").write_text(json.dumps(doc))
    one_line_error("map", "correct", "--model", "struts2", "--map", tmp_path / "levels.json", "--joints",
                   d / "m_si.csv", "--out", tmp_path / "o.csv", contains=["mesh.levels"])
    model = tmp_path / "other.yaml"
    model.write_text(_struts_file(0.401))
    one_line_error("map", "correct", "--model", model, "--map", d / "si.json", "--joints", d / "m_si.csv", "--out",
                   tmp_path / "o.csv", contains=["differs from the one the map was built with: pivot.2.x"])


def _struts_file(pivot2_x):
    return (f"format: station-model/1\nname: struts2\nkind: parallel\nunits: {{length: m, angle: rad}}\n"
            f"parallel:\n  type: planar-struts\n  pivots: [[0, 0], [{pivot2_x}, 0]]\n"
            f"  struts: {{limits: [[0.3, 0.5], [0.3, 0.5]], max_velocity: 0.05, max_acceleration: 0.5}}\n"
            f"  branch: 1\n")


@pytest.mark.slow
def test_hexapod_with_mm_deg_files_and_the_installed_command(tmp_path):
    w = World.default("hexapod", seed=2)
    ok("map", "plan", "--model", "hexapod", "--grid", "1", "--mesh", "simplex", "--out", tmp_path / "plan.csv")
    _, x = read_csv(tmp_path / "plan.csv")
    T = w.truth.fk(x, guess=w.nominal.fk(x))
    measured_file(tmp_path / "m.csv", x, T, planar=False, mm=True)
    p = station_proc("map", "build", "--model", "hexapod", "--samples", tmp_path / "m.csv", "--mesh", "simplex",
                     "--out", tmp_path / "map.json")
    assert p.code == 0, p.err
    doc = json.loads((tmp_path / "map.json").read_text())
    assert doc["mesh"]["type"] == "simplex" and doc["pose"] == list(FULL)
    rng = np.random.default_rng(4)
    q = w.nominal.lower + 0.005 + (w.nominal.upper - w.nominal.lower - 0.01) * rng.uniform(0, 1, (25, 6))
    P = w.truth.fk(q)
    v = se3.matrix_to_pose(P, "rotvec")
    write_csv(tmp_path / "t.csv", ["x[mm]", "y[mm]", "z[mm]", "rx[deg]", "ry[deg]", "rz[deg]"],
              np.hstack([v[:, :3] * 1e3, np.degrees(v[:, 3:])]))
    ok("map", "apply", "--model", "hexapod", "--map", tmp_path / "map.json", "--poses", tmp_path / "t.csv", "--out",
       tmp_path / "c.csv")
    _, c = read_csv(tmp_path / "c.csv")
    before = np.linalg.norm(w.truth.fk(w.nominal.ik_closed(P)[0], guess=P)[:, :3, 3] - P[:, :3, 3], axis=1)
    after = np.linalg.norm(w.truth.fk(c, guess=P)[:, :3, 3] - P[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(after ** 2)) < 0.1 * np.sqrt(np.mean(before ** 2))
    write_csv(tmp_path / "r.csv", [f"x{i}" for i in range(1, 7)], q)
    ok("map", "correct", "--model", "hexapod", "--map", tmp_path / "map.json", "--joints", tmp_path / "r.csv",
       "--out", tmp_path / "p.csv")
    header, pose = read_csv(tmp_path / "p.csv")
    assert header == list(FULL)
    assert np.sqrt(np.mean(np.sum((pose[:, :3] - v[:, :3]) ** 2, axis=1))) < 0.1 * np.sqrt(np.mean(before ** 2))


@pytest.mark.slow
def test_map_on_top_of_a_parametric_calibration(tmp_path):
    """arm6 with hidden geometry and a gravity-loaded compliant shoulder: station solve identifies the geometry,
    the map is built on top of that result (and, for comparison, on the nominal model); both reach held-out
    targets on the true arm."""
    from station.solver import Observations, solve

    w = World.default("arm6", seed=7, errors={"explicit": {"offset.j2": 0.002, "offset.j3": -0.0015,
                                                             "dh.j2.a": 4e-4, "dh.j3.a": -3e-4}},
                      joints={"compliance": {"j2": 3e-5, "j3": 3e-5}, "payload": 20.0})
    nom = w.nominal
    lo, hi = np.radians([-20, -10, -10, -30, -70, -30]), np.radians([20, 30, 30, 30, -30, 30])
    rng = np.random.default_rng(1)
    qs = lo + (hi - lo) * rng.uniform(0, 1, (60, 6))

    def pose(q):
        w.command_q(q)
        return w.tip_pose_true()

    meas = np.array([pose(q)[:3, 3] for q in qs])
    res = solve(nom, Observations(qs, np.full(60, "A", dtype=object), meas), "offset.j2,offset.j3,dh.j2.a,dh.j3.a",
                instrument_frame="base")
    (tmp_path / "cal.json").write_text(json.dumps(res.to_dict()))
    limited = tmp_path / "arm6-cell.yaml"
    doc = station_proc("model", "export", "arm6", "--units", "m,rad", "--out", limited)
    assert doc.code == 0, doc.err
    import yaml

    m = yaml.safe_load(limited.read_text())
    for j, a, b in zip(m["joints"], lo, hi, strict=True):
        j["limits"] = [float(a), float(b)]
    limited.write_text(yaml.safe_dump(m, sort_keys=False))
    ok("map", "plan", "--model", limited, "--grid", "1", "--out", tmp_path / "plan.csv")
    _, x = read_csv(tmp_path / "plan.csv")
    measured_file(tmp_path / "m.csv", x, np.array([pose(q) for q in x]), planar=False)
    ok("map", "build", "--model", limited, "--samples", tmp_path / "m.csv", "--out", tmp_path / "plain.json")
    out = ok("map", "build", "--model", limited, "--samples", tmp_path / "m.csv", "--calibration",
             tmp_path / "cal.json", "--out", tmp_path / "both.json")
    assert "on top of calibration cal.json" in out
    plain, both = (json.loads((tmp_path / f).read_text()) for f in ("plain.json", "both.json"))
    # the map carries exactly what the solve identified (the gravity sag the geometry cannot explain leaves some
    # length weak against its prior: the solver says so and keeps it nominal)
    assert set(both["calibration"]["parameters"]) == set(res.identified) and {"offset.j2", "dh.j2.a"} <= set(
        res.identified)
    assert np.abs(np.subtract(both["samples"]["summand"], plain["samples"]["summand"])).max() > 1e-4
    # held-out targets inside the box, reached by the true arm
    qt = lo + (hi - lo) * (0.15 + 0.7 * rng.uniform(0, 1, (15, 6)))
    v = se3.matrix_to_pose(nom.fk(qt), "rotvec")
    write_csv(tmp_path / "t.csv", list(FULL), v)
    errors = {}
    for name in ("plain", "both"):
        ok("map", "apply", "--model", limited, "--map", tmp_path / f"{name}.json", "--poses", tmp_path / "t.csv",
           "--out", tmp_path / f"c_{name}.csv")
        _, c = read_csv(tmp_path / f"c_{name}.csv")
        errors[name] = np.linalg.norm([pose(ci)[:3, 3] for ci in c] - v[:, :3], axis=1)
    before = np.linalg.norm([pose(q)[:3, 3] for q in qt] - v[:, :3], axis=1)
    for name, e in errors.items():
        assert np.sqrt(np.mean(e ** 2)) < 0.15 * np.sqrt(np.mean(before ** 2)), (name, e, before)
    one_line_error("map", "build", "--model", "struts2", "--samples", tmp_path / "m.csv", "--calibration",
                   tmp_path / "cal.json", "--out", tmp_path / "x.json", contains=["cal.json", "arm6"])


@pytest.mark.parametrize("span", ["0", "-5", "120", "nan"])
def test_run_span_deg_out_of_range_is_one_line_before_any_robot(span, tmp_path):
    # --span-deg (correction_map on a serial arm) is checked before the robot URL is even opened
    one_line_error("run", "correction_map", "--robot", "canopen+virtual://nowhere?nodes=1-6&model=arm6",
                   "--serial", "X1", "--span-deg", span, contains=("--span-deg",))


def test_run_span_deg_reaches_the_procedure_options():
    from station.cli.run_cmd import _options

    assert _options(None, None, None, None, None, span_deg=10)["span_deg"] == 10.0
    assert "span_deg" not in _options(None, None, None, None, None)
