"""``station solve`` / ``station fk`` end to end through the installed command (subprocess)."""

import json

import numpy as np
import pytest
from clirunner import station_proc

from station.kinematics import load_model
from station.solver.simulate import touch_observations

UR_HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
HIDDEN = {"offset.j2": 0.004, "offset.j3": -0.003, "offset.j4": 0.005, "offset.j5": -0.002, "tcp.z": 0.1013}


def write(path, q, units="deg", labels=None):
    k = 180 / np.pi if units == "deg" else 1.0
    head = ",".join(f"q{j + 1}[{units}]" for j in range(q.shape[1]))
    rows = [",".join(f"{v * k:.12g}" for v in r) + (f",{labels[i]}" if labels is not None else "")
            for i, r in enumerate(q)]
    path.write_text(head + (",point" if labels is not None else "") + "\n" + "\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    nominal = load_model("ur5e").with_params({"tcp.z": 0.1})
    truth = nominal.with_params(HIDDEN)
    c = truth.position(UR_HOME)
    rng = np.random.default_rng(21)
    obs = touch_observations(truth, {"A": c}, 30, rng, centre=UR_HOME, spread=0.3)
    ho = touch_observations(truth, {"A": c}, 8, rng, centre=UR_HOME, spread=0.3)
    write(d / "s_deg.csv", obs.q, "deg", obs.point)
    write(d / "s_rad.csv", obs.q, "rad")
    write(d / "ho.csv", ho.q, "deg", ho.point)
    return d, c


def test_solve_end_to_end(data):
    d, c = data
    code, out, err = station_proc("solve", "--model", "ur5e", "--samples", "s_deg.csv", "--identify", "offsets,tcp",
                                  "--tool", "0,0,100mm", "--holdout", "ho.csv", "--out", "r.json", cwd=d)
    assert code == 0, err
    assert "not identifiable" in out and "offset.j1: a rotation about joint 1 moves the unknown point" in out
    doc = json.loads((d / "r.json").read_text())
    P = doc["parameters"]
    assert not P["offset.j1"]["identifiable"] and P["offset.j1"]["std"] is None
    assert not P["offset.j6"]["identifiable"] and "joint 6" in P["offset.j6"]["reason"]
    for n, v in HIDDEN.items():
        assert abs(P[n]["value"] - v) < 4 * P[n]["std"], n
    assert {"point.A.x", "point.A.y", "point.A.z"} <= set(P)
    assert doc["rank"] == 10 and doc["n_parameters"] == 12 and doc["converged"] is True
    assert doc["residuals"]["rms_after_m"] < 1e-4 < doc["residuals"]["rms_before_m"]
    assert doc["holdout"]["n_samples"] == 8 and doc["holdout"]["rms_m"] < 1e-4

    # the same data in radians without a point column: the same answer
    code, _, err = station_proc("solve", "--model", "ur5e", "--samples", "s_rad.csv", "--tool", "0,0,0.1", "--out",
                                "r2.json", cwd=d)
    assert code == 0, err
    P2 = json.loads((d / "r2.json").read_text())["parameters"]
    for n in HIDDEN:
        assert P2[n]["value"] == pytest.approx(P[n]["value"], abs=1e-9)

    # known point given in mm: joint 1 becomes identifiable
    ref = ",".join(f"{v * 1e3:.9f}" for v in c) + "mm"
    code, out, err = station_proc("solve", "--model", "ur5e", "--samples", "s_deg.csv", "--reference", ref, "--tool",
                                  "0,0,0.1", "--out", "r3.json", cwd=d)
    assert code == 0, err
    P3 = json.loads((d / "r3.json").read_text())["parameters"]
    assert P3["offset.j1"]["identifiable"] and abs(P3["offset.j1"]["value"]) < 4 * P3["offset.j1"]["std"]
    assert "point.A.x" not in P3

    # fk with the calibration reproduces the touched point
    code, out, err = station_proc("fk", "--model", "ur5e", "--tool", "0,0,0.1", "--calibration", "r3.json", "--joints",
                                  "s_deg.csv", "--out", "fk.csv", cwd=d)
    assert code == 0, err
    lines = [ln for ln in (d / "fk.csv").read_text().splitlines() if not ln.startswith("#")]
    assert lines[0] == "x[m],y[m],z[m],rx[rad],ry[rad],rz[rad]"
    xyz = np.array([[float(v) for v in ln.split(",")[:3]] for ln in lines[1:]])
    assert len(xyz) == 30 and np.max(np.linalg.norm(xyz - c, axis=1)) < 1e-4
    code, out, _ = station_proc("fk", "--model", "ur5e", "--joints", "s_deg.csv", cwd=d)  # nominal, to stdout
    assert code == 0 and out.splitlines()[1].startswith("x[m]")


@pytest.mark.parametrize("content, args, message", [
    ("q1,q2,q3,q4,q5\n" + "0,0,0,0,0\n" * 20, (), "bad.csv: missing column 'q6'"),
    ("q1,q2,q3,q4,q5,q6,q7\n" + "0,0,0,0,0,0,0\n" * 20, (), "bad.csv: wrong joint count"),
    ("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n0,0,nan,0,0,0\n", (), "bad.csv:3: column 'q3': not a finite number"),
    ("q1,q2,q3,q4,q5,q6\n0,-1,1,0,1,0\n0.5,-1,1,0,1,0\n1,-1,1,0,1,0\n", (),
     "3 samples give 9 equations for 12 unknowns"),
    (None, ("--identify", "offsets,tcpp"), "--identify 'offsets,tcpp': unknown parameter or group 'tcpp'"),
    (None, ("--reference", "1,2"), "--reference '1,2': expected x,y,z"),
    (None, ("--model", "nosuchrobot"), "unknown model 'nosuchrobot'"),
])
def test_bad_input_exits_2_with_one_line(data, content, args, message):
    d, _ = data
    samples = "s_deg.csv"
    if content is not None:
        (d / "bad.csv").write_text(content)
        samples = "bad.csv"
    argv = ["solve", "--model", "ur5e", "--samples", samples, *args]
    if "--model" in args:
        argv = ["solve", "--samples", samples, *args]
    code, out, err = station_proc(*argv, cwd=d)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("station: error: "), err
    assert message in lines[0]


def test_fk_rejects_calibration_of_another_model(data):
    d, _ = data
    (d / "other.json").write_text(json.dumps({"model": "ur10e", "parameters": {}, "residuals": {}, "rank": 0,
                                              "n_parameters": 0, "converged": True, "iterations": 0}))
    code, _, err = station_proc("fk", "--model", "ur5e", "--calibration", "other.json", "--joints", "s_deg.csv", cwd=d)
    assert code == 2 and "ur10e" in err and err.startswith("station: error: ")


def test_solve_exit_codes_prior_noise_loss(data):
    """0 trusted (also where the data overrule a too-tight prior, reported); 2 bad --prior/--noise/--loss, one
    line."""
    d, _ = data
    base = ("solve", "--model", "ur5e", "--samples", "s_deg.csv", "--identify", "offsets,tcp", "--tool", "0,0,100mm")
    code, out, err = station_proc(*base, "--noise", "20um", "--prior", "offsets=0.5deg", "--prior", "tcp=5mm",
                                  "--loss", "huber", "--out", "ok.json", cwd=d)
    assert code == 0, err
    doc = json.loads((d / "ok.json").read_text())
    assert doc["trusted"] is True and doc["solve_time_s"] > 0
    assert doc["parameters"]["offset.j2"]["prior_std"] == pytest.approx(0.5 * np.pi / 180)
    assert doc["parameters"]["tcp.z"]["prior_std"] == pytest.approx(5e-3)
    assert "result: trusted" in out
    # the data need offsets of 4-5 mrad that a 0.01 deg prior forbids: a prior-data conflict the data settle,
    # named with the data's estimate and std, estimated from the data alone (reported), exit 0
    code, out, err = station_proc(*base, "--prior", "offsets=0.01deg", "--out", "conflict.json", cwd=d)
    assert code == 0, (out, err)
    doc = json.loads((d / "conflict.json").read_text())
    assert doc["trusted"] is True and doc["conflicts"] and all(c["freed"] for c in doc["conflicts"])
    assert "note: prior-data conflict: offset.j" in out and "estimated from the data alone" in out
    for opt, val in (("--prior", "offsets"), ("--prior", "offsets=abc"), ("--prior", "offsets=-1deg"),
                     ("--prior", "nosuch=1mm"), ("--noise", "5deg"), ("--noise", "0um"), ("--loss", "cauchy")):
        code, out, err = station_proc(*base, opt, val, cwd=d)
        assert code == 2, (opt, val, out, err)
        assert err.startswith("station: error: ") and len(err.strip().splitlines()) == 1 and opt in err, err


def test_an_excluded_outlier_is_named_by_its_1_based_row(tmp_path):
    """A slipped touch (truth: the one row we disturbed) is excluded and printed with the row number the samples
    reader's own messages use (1-based), while the JSON keeps the 0-based index."""
    nominal = load_model("ur5e").with_params({"tcp.z": 0.1})
    truth = nominal.with_params(HIDDEN)
    rng = np.random.default_rng(5)
    obs = touch_observations(truth, {"A": truth.position(UR_HOME)}, 30, rng, centre=UR_HOME, spread=0.3)
    q = obs.q + rng.normal(0.0, 2e-5, obs.q.shape)  # encoder-class noise (~20 um at the tool)
    q[7, 1] += 0.01  # row 8 of the file: a slipped touch, ~5 mm off
    write(tmp_path / "s.csv", q, "rad")
    code, out, err = station_proc("solve", "--model", "ur5e", "--samples", "s.csv", "--identify", "offsets",
                                  "--tool", "0,0,100mm", "--out", "r.json", cwd=tmp_path)
    res = json.loads((tmp_path / "r.json").read_text())
    assert [o["index"] for o in res["outliers"]] == [7], (out, err)
    assert "  row 8 point A:" in out
