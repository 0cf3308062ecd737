"""``station iso9283 --samples FILE --out RESULT.json`` as a user runs it (a subprocess): a tracker's export with
units in the headers (mm, deg) in, the JSON per pose in SI out, equal to the standard's formulas computed here
independently; bad files are one line naming file, line and column, exit 2, nothing written."""

import json

import numpy as np
import pytest
from clirunner import station_main, station_proc

from station.kinematics import se3

POSES = {"P1": (400, 0, 500), "P2": (480, 80, 420), "P3": (320, 80, 420), "P4": (320, -80, 580),
         "P5": (480, -80, 580)}  # mm


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """30 cycles of five poses (+ P1 from two more directions), mm and deg, like a tracker's CSV export."""
    rng = np.random.default_rng(5)
    rows = ["# tracker export: commanded and attained tool poses, robot base frame",
            "pose,cycle,direction,x_c[mm],y_c[mm],z_c[mm],rx_c[deg],ry_c[deg],rz_c[deg],x[mm],y[mm],z[mm],"
            "rx[deg],ry[deg],rz[deg],temperature"]
    truth = {}
    rc = np.array([180.0, 0.0, 0.0])  # tool pointing down
    for p, c in POSES.items():
        bias = rng.normal(0, 0.2, 3)
        truth[p] = bias
        for d, shift in (("-z", 0.0), ("-x", 0.03), ("-y", -0.02)):
            if d != "-z" and p != "P1":
                continue
            for k in range(1, 31):
                a = np.array(c) + bias + shift + rng.normal(0, 0.015, 3)
                R = se3.rotvec_to_matrix(np.radians(rng.normal(0, 0.004, 3))) @ se3.rotvec_to_matrix(np.radians(rc))
                ra = np.degrees(se3.matrix_to_rotvec(R))
                rows.append(",".join([p, str(k), d, *(f"{v:.6f}" for v in (*c, *rc, *a, *ra)), "21.5"]))
    path = tmp_path_factory.mktemp("iso") / "export.csv"
    path.write_text("\n".join(rows) + "\n")
    return path, truth


def test_result_json_per_pose_in_si(export, tmp_path):
    path, _ = export
    out = tmp_path / "result.json"
    r = station_proc("iso9283", "--samples", str(path), "--out", str(out), "--noise", "15um")
    assert r.code == 0, r.err
    assert "RP_l" in r.out and "P1" in r.out
    res = json.loads(out.read_text())
    assert res["format"] == "station-iso9283/1" and res["units"] == "SI (m, rad)"
    assert res["source"]["direction"] == "-z" and res["source"]["cycles"]["P1"] == 30
    # independent computation from the file (pandas-free: numpy on the parsed CSV)
    rows = [line.split(",") for line in path.read_text().splitlines()[2:]]
    for p, c in POSES.items():
        mine = np.array([[float(v) for v in row[9:12]] for row in rows if row[0] == p and row[2] == "-z"]) * 1e-3
        bary = mine.mean(axis=0)
        assert res["poses"][p]["AP_p"] == pytest.approx(np.linalg.norm(bary - np.array(c) * 1e-3), rel=1e-9)
        lj = np.linalg.norm(mine - bary, axis=1)
        assert res["poses"][p]["RP_l"] == pytest.approx(lj.mean() + 3 * lj.std(ddof=1), rel=1e-9)
        lo, hi = res["poses"][p]["RP_l_ci"]
        assert lo < res["poses"][p]["RP_l"] < hi
        assert res["poses"][p]["RP_a"] < 3 * np.radians(0.004) * 2  # 3 sigma of 0.004 deg, in rad
    assert "vAP_p" in res["poses"]["P1"] and "vAP_p" not in res["poses"]["P2"]
    assert set(res["poses"]["P1"]["directions"]) == {"-x", "-y", "-z"}
    d = res["distance"]
    assert d["poses"] == ["P2", "P4"] and d["D_c"] == pytest.approx(np.linalg.norm(
        np.subtract(POSES["P2"], POSES["P4"])) * 1e-3, rel=1e-12)
    assert res["instrument"]["sigma_m"] == pytest.approx(15e-6)
    assert res["summary"]["AP_p"]["value"] == max(res["poses"][p]["AP_p"] for p in POSES)


def test_mm_and_m_give_the_same_answer(export, tmp_path):
    path, _ = export
    text = path.read_text().splitlines()
    head = text[1].replace("[mm]", "").replace("[deg]", "[rad]")
    body = []
    for line in text[2:]:
        f = line.split(",")
        f[3:6] = [f"{float(v) * 1e-3:.12g}" for v in f[3:6]]
        f[6:9] = [f"{np.radians(float(v)):.15g}" for v in f[6:9]]
        f[9:12] = [f"{float(v) * 1e-3:.12g}" for v in f[9:12]]
        f[12:15] = [f"{np.radians(float(v)):.15g}" for v in f[12:15]]
        body.append(",".join(f))
    si = tmp_path / "si.csv"
    si.write_text("\n".join([head, *body]) + "\n")
    from station.cli.iso_cmd import evaluate_file  # what the command evaluates, in process

    ra, rb = evaluate_file(path), evaluate_file(si)
    for p in POSES:
        for key in ("AP_p", "RP_l", "AP_a", "RP_c"):
            assert ra["poses"][p][key] == pytest.approx(rb["poses"][p][key], rel=1e-6, abs=1e-12)


@pytest.mark.parametrize("edit, expect", [
    (lambda t: t.replace("x_c[mm]", "x_c[deg]"), "export.csv:2: column 'x_c[deg]': it is a length"),
    (lambda t: t.replace(",y_c[mm]", ",yc[mm]"), "export.csv:2: missing column 'y_c'"),
    (lambda t: t.replace(",rz[deg]", ",rzz[deg]"), "export.csv:2: missing column 'rz'"),
    (lambda t: t.replace("P1,2,-z,400.000000", "P1,2,-z,400.500000"), "export.csv:4: pose P1: commanded pose differs"),
    (lambda t: t.replace("P1,2,-z", "P1,1,-z"), "export.csv:4: pose P1 cycle 1 direction -z is also on line 3"),
    (lambda t: t.replace("P1,3,-z", "P1,three,-z"), "export.csv:5: column 'cycle': not an integer ('three')"),
])
def test_bad_files_are_one_line_and_write_nothing(export, tmp_path, edit, expect):
    """In process (``station.cli.main``, as the console script runs it): one line, exit 2, nothing written."""
    path, _ = export
    bad = tmp_path / "export.csv"
    bad.write_text(edit(path.read_text()))
    out = tmp_path / "r.json"
    r = station_main("iso9283", "--samples", bad, "--out", out)
    assert r.code == 2 and not out.exists()
    lines = r.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: ") and expect in lines[0], lines
