"""``station compensate``: targets in the base frame -> joint commands (or corrected Cartesian targets) for a
controller that keeps its nominal model. On an emulated arm6 (CiA 402 drives on a virtual CAN channel, real canopen
library) with hidden geometry errors: a calibration from tracker readings (``station solve``, the tracker's frame
surveyed), then the compensated commands driven through the driver: the TRUE tool lands on each target within
3 x the predicted uncertainty, and the RMS error falls by more than 90 % against the nominal commands. The
predicted uncertainty itself is calibrated: over Monte Carlo worlds, E|e|^2 / sigma^2 is about 1."""

import csv
import uuid
from pathlib import Path

import numpy as np
import pytest
from clirunner import station_main, station_proc
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.tracker.config import tracker_config
from station.mocks.world import World
from station.mocks.world.tracker import measure_poses

import station
from station.kinematics import se3
from station.performance.compensate import Design, compensate, pose_covariance, predictive_covariance
from station.solver import Observations, solve

GOOD = np.array([0.0, 0.17, 0.17, 0.0, -0.87, 0.0])


def _tracker_samples(world, cfg, n, rng, span=np.radians(30)):
    """``n`` tracker readings around the work zone, in the base frame (the tracker's placement surveyed)."""
    q = GOOD + rng.uniform(-span, span, (n, 6))
    read, meas = [], []
    for qi in q:
        world.command_q(qi)
        read.append(world.encoder_q())
        M = measure_poses(world.tip_pose_true()[None], cfg.reflectors, cfg.tracker_in_base, rng)[0]
        meas.append((cfg.tracker_in_base @ M)[:3, 3])
    return np.array(read), np.array(meas)


def _csv(path: Path, header, rows):
    path.write_text(",".join(header) + "\n" + "".join(",".join(f"{v:.12g}" if not isinstance(v, str) else v
                                                             for v in r) + "\n" for r in rows))


def _read(path):
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    rows = list(csv.reader(lines))
    return rows[0], rows[1:]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("comp")
    world = World.default("arm6", seed=7, start=GOOD.tolist())
    cfg = tracker_config({})
    q, meas = _tracker_samples(world, cfg, 60, np.random.default_rng(3))
    world.command_q(GOOD)
    samples = tmp / "samples.csv"
    _csv(samples, [f"q{k}[rad]" for k in range(1, 7)] + ["x[m]", "y[m]", "z[m]"], np.column_stack([q, meas]))
    result = tmp / "result.json"
    r = station_proc("solve", "--model", "arm6", "--samples", str(samples), "--identify", "offsets,dh,tcp",
                     "--instrument-frame", "base", "--out", str(result))
    assert r.code == 0, r.err
    rng = np.random.default_rng(8)
    qt = GOOD + rng.uniform(-np.radians(20), np.radians(20), (20, 6))
    T = world.nominal.fk(qt)  # targets the nominal model reaches: in the base frame, mm and deg in the file
    v = se3.matrix_to_pose(T, "rotvec")
    targets = tmp / "targets.csv"
    rows = [[f"T{i + 1}", *(v[i, :3] * 1e3), *np.degrees(v[i, 3:])] for i in range(len(v))]
    rows.append(["far", 5000.0, 0.0, 500.0, *np.degrees(v[0, 3:])])  # out of reach
    _csv(targets, ["name", "x[mm]", "y[mm]", "z[mm]", "rx[deg]", "ry[deg]", "rz[deg]"], rows)
    return {"world": world, "result": result, "targets": targets, "T": T, "qt": qt, "tmp": tmp}


def test_compensated_commands_bring_the_true_tool_onto_the_targets(calibrated, tmp_path):
    c = calibrated
    out, script = tmp_path / "commands.csv", tmp_path / "program.script"
    start = ",".join(f"{np.degrees(v):.6f}" for v in GOOD) + "deg"
    r = station_proc("compensate", "--model", "arm6", "--calibration", str(c["result"]), "--poses", str(c["targets"]),
                     "--out", str(out), "--start", start, "--urscript", str(script))
    assert r.code == 1, r.err  # one target out of reach: named, every other row written
    err = r.err.strip().splitlines()
    assert len(err) == 1 and "1 of 21 targets unreachable: row 21" in err[0] and "targets.csv:22" in err[0]
    assert "posterior of its 60 samples" in r.out
    head, rows = _read(out)
    assert head[:3] == ["row", "name", "status"] and head[3:9] == [f"q{k}[rad]" for k in range(1, 7)]
    assert [row[2] for row in rows[:20]] == ["ok"] * 20 and rows[20][2].startswith("unreachable")
    assert rows[20][3:9] == [""] * 6  # no command for it
    q = np.array([[float(x) for x in row[3:9]] for row in rows[:20]])
    sigma = np.array([float(row[head.index("sigma[m]")]) for row in rows[:20]])
    # the commands driven through the real driver; the truth is where the world's true tool goes
    world = c["world"]
    channel = f"cp{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(world, "virtual", channel).start()
    try:
        with station.connect(f"canopen+virtual://{channel}?nodes=1-6&model=arm6&sdo_timeout_ms=2000"
                             "&heartbeat_ms=1000") as robot:
            robot.enable()
            e_comp, e_nom = [], []
            for i in range(20):
                robot.move_joints(q[i])
                e_comp.append(np.linalg.norm(world.tip_pose_true()[:3, 3] - c["T"][i, :3, 3]))
                robot.move_joints(c["qt"][i])  # the same target through the nominal model
                e_nom.append(np.linalg.norm(world.tip_pose_true()[:3, 3] - c["T"][i, :3, 3]))
    finally:
        emu.stop()
    e_comp, e_nom = np.array(e_comp), np.array(e_nom)
    assert np.all(e_comp <= 3 * sigma), np.round(e_comp / sigma, 2)
    rms_c, rms_n = np.sqrt(np.mean(e_comp ** 2)), np.sqrt(np.mean(e_nom ** 2))
    assert rms_c < 0.1 * rms_n, (rms_c, rms_n)
    # the URScript program: one movej per reached target, the unreachable one a comment
    text = script.read_text()
    assert text.startswith("def station_compensated():") and text.rstrip().endswith("end")
    assert text.count("movej(") == 20 and "# target 21: not moved (unreachable" in text


def test_cartesian_targets_come_back_to_the_same_joints_through_the_nominal_model(calibrated, tmp_path):
    c = calibrated
    joints, cart = tmp_path / "j.csv", tmp_path / "c.csv"
    common = ["--model", "arm6", "--calibration", str(c["result"]), "--poses", str(c["targets"]), "--start",
              ",".join(str(v) for v in GOOD)]
    assert station_proc("compensate", *common, "--out", str(joints)).code == 1
    assert station_proc("compensate", *common, "--out", str(cart), "--cartesian", "--units", "mm,deg").code == 1
    hj, rj = _read(joints)
    hc, rc = _read(cart)
    assert hc[3:9] == ["x[mm]", "y[mm]", "z[mm]", "rx[deg]", "ry[deg]", "rz[deg]"]
    q = np.array([[float(x) for x in row[3:9]] for row in rj[:20]])
    v = np.array([[float(x) for x in row[3:9]] for row in rc[:20]])
    T = se3.pose_to_matrix(np.column_stack([v[:, :3] * 1e-3, np.radians(v[:, 3:])]))
    nominal = c["world"].nominal
    back = nominal.ik(T, q + 1e-3, tol_pos=1e-12, tol_rot=1e-12)  # what the controller's own IK gives
    assert np.max(np.abs(back.q - q)) < 1e-6


def test_a_report_alone_gives_the_conservative_uncertainty(calibrated, tmp_path):
    """A session's report.json without its journal: the parameters' stds only (stated in the output)."""
    import json

    from station.report.content import build_report

    c = calibrated
    res = json.loads(c["result"].read_text())
    report = build_report({"session": "s1", "model": "arm6", "result": res, "samples": []})
    rp = tmp_path / "report.json"
    rp.write_text(json.dumps(report))
    out = tmp_path / "o.csv"
    r = station_proc("compensate", "--model", "arm6", "--calibration", str(rp), "--poses", str(c["targets"]), "--out",
                     str(out), "--start", ",".join(str(v) for v in GOOD))
    assert r.code == 1 and "samples not found: conservative" in r.out
    head, rows = _read(out)
    assert float(rows[0][head.index("sigma[m]")]) > 0


@pytest.mark.parametrize("args, expect", [
    (["--calibration", "missing.json"], "no journal"),
    (["--start", "1,2,3"], "--start '1,2,3': expected 6 joint values"),
    (["--units", "furlong,deg"], "--units 'furlong,deg'"),
])
def test_bad_input_is_one_line(calibrated, tmp_path, args, expect):
    """In process (``station.cli.main``, as the console script runs it): one line, exit 2, nothing written."""
    c = calibrated
    base = {"--calibration": str(c["result"]), "--poses": str(c["targets"]), "--out": str(tmp_path / "o.csv")}
    for k in range(0, len(args), 2):
        base[args[k]] = args[k + 1]
    r = station_main("compensate", "--model", "arm6", *[x for kv in base.items() for x in kv])
    assert r.code == 2 and not (tmp_path / "o.csv").exists()
    lines = r.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: ") and expect in lines[0], lines


@pytest.mark.slow  # 12 worlds x (60-sample solve + 20 targets): ~20 s
def test_predicted_uncertainty_is_calibrated_over_monte_carlo():
    """Across worlds with different hidden errors and tracker noise: the compensated pose's 3-D error against the
    world's truth over the predicted sigma (3-D RMS) has E[|e|^2 / sigma^2] near 1 (a chi-square-like band for
    240 targets), and none beyond 4 sigma."""
    cfg = tracker_config({})
    ratios = []
    for seed in range(12):
        world = World.default("arm6", seed=100 + seed, start=GOOD.tolist())
        rng = np.random.default_rng(seed)
        q, meas = _tracker_samples(world, cfg, 60, rng)
        res = solve(world.nominal, Observations(q, np.array(["P"] * 60, dtype=object), meas),
                    identify="offsets,dh,tcp", instrument_frame="base")
        assert res.trusted, res.failure
        cal = res.calibrated(world.nominal)
        design = Design(q, np.array(["P"] * 60, dtype=object), True, True, res.noise["sigma_m"],
                        {n: p.prior_std for n, p in res.parameters.items() if p.kind == "model" and p.prior_std})
        cov, names = predictive_covariance(cal, design)
        T = world.nominal.fk(GOOD + rng.uniform(-np.radians(20), np.radians(20), (20, 6)))
        comp = compensate(world.nominal, cal, T, covariance=cov, names=names, start=GOOD)
        assert comp.ok.all()
        S = pose_covariance(cal, comp.q, cov, names)
        sigma = np.sqrt(np.trace(S[:, :3, :3], axis1=1, axis2=2))
        assert np.allclose(sigma, comp.sigma)
        for i in range(len(T)):
            world.command_q(comp.q[i])
            ratios.append(np.linalg.norm(world.tip_pose_true()[:3, 3] - T[i, :3, 3]) / sigma[i])
    r2 = np.mean(np.square(ratios))
    assert 0.6 < r2 < 1.6, r2  # errors within a world are correlated: a wide band, a mis-scaled sigma falls out
    assert max(ratios) < 4.0


@pytest.mark.slow  # ~10 s: a scripted session on the emulated arm6 with the tracker, then a solve
def test_calibration_from_a_session(calibrated, tmp_path, monkeypatch):
    """``--calibration SESSION``: the session's solve result, its samples weigh the uncertainty (the tracker frame
    solved as a nuisance there: the readings are in the instrument's frame)."""
    from station.mocks.tracker.server import TrackerServer

    from station.engine.plan import PlannedPose

    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world = World.default("arm6", seed=9, start=GOOD.tolist())
    channel = f"cs{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(world, "virtual", channel).start()
    rng = np.random.default_rng(4)
    try:
        with TrackerServer(world, tracker_config({}), seed=2) as trk, station.session(
                f"canopen+virtual://{channel}?nodes=1-6&model=arm6&serial=CS1&sdo_timeout_ms=2000&heartbeat_ms=1000",
                "CS1", name="tracker_calibration", options={"tracker": trk.url}, db=f"sqlite:///{tmp_path}/r.db",
                report=False) as s:
            tracker = s.instrument("tracker")
            for i, q in enumerate(GOOD + rng.uniform(-np.radians(25), np.radians(25), (50, 6))):
                s.move_to(q)
                s.measure_pose(PlannedPose(i, "P", q.tolist(), q.tolist()), tracker)
            res = s.solve(identify="offsets,dh,tcp")
            assert res.trusted, res.failure
            sid = s.id
    finally:
        emu.stop()
    out = tmp_path / "o.csv"
    r = station_proc("compensate", "--model", "arm6", "--calibration", sid,
                     "--poses", str(calibrated["targets"]), "--out", str(out), "--start",
                     ",".join(str(v) for v in GOOD), env={"STATION_HOME": str(tmp_path / "home")})
    assert r.code == 1 and "posterior of its 50 samples" in r.out, r.out + r.err
    head, rows = _read(out)
    assert [row[2] for row in rows[:20]] == ["ok"] * 20



@pytest.mark.slow
def test_a_seven_axis_franka_gets_compensated_joint_targets(tmp_path):
    """A Franka arm keeps its own kinematics (no write-back): the calibration is used by compensating targets.
    7 joints: the redundant IK starts from the robot's configuration; the truth is the world's true tool."""
    start = np.array([0.0, -0.4, 0.0, -2.1, 0.0, 1.7, 0.8])
    world = World.default("fr3", seed=11, start=start.tolist())
    cfg = tracker_config({})
    rng = np.random.default_rng(5)
    q = start + rng.uniform(-0.4, 0.4, (70, 7))
    read, meas = [], []
    for qi in q:
        world.command_q(qi)
        read.append(world.encoder_q())
        M = measure_poses(world.tip_pose_true()[None], cfg.reflectors, cfg.tracker_in_base, rng)[0]
        meas.append((cfg.tracker_in_base @ M)[:3, 3])
    samples, result = tmp_path / "samples.csv", tmp_path / "result.json"
    _csv(samples, [f"q{k}[rad]" for k in range(1, 8)] + ["x[m]", "y[m]", "z[m]"],
         np.column_stack([read, meas]))
    r = station_proc("solve", "--model", "fr3", "--samples", str(samples), "--identify", "offsets,dh,tcp",
                     "--instrument-frame", "base", "--out", str(result))
    assert r.code == 0, r.err
    qt = start + rng.uniform(-0.3, 0.3, (12, 7))
    T = world.nominal.fk(qt)
    targets, out = tmp_path / "targets.csv", tmp_path / "commands.csv"
    _csv(targets, ["x[m]", "y[m]", "z[m]"], T[:, :3, 3])
    r = station_proc("compensate", "--model", "fr3", "--calibration", str(result), "--poses", str(targets),
                     "--out", str(out), "--start", ",".join(f"{v:.6f}" for v in start))
    assert r.code == 0, r.err
    head, rows = _read(out)
    assert [row[1] for row in rows] == ["ok"] * 12
    cols = [head.index(f"q{k}[rad]") for k in range(1, 8)]
    sigma = np.array([float(row[head.index("sigma[m]")]) for row in rows])
    e_comp, e_nom = [], []
    for i, row in enumerate(rows):
        world.command_q(np.array([float(row[c]) for c in cols]))
        e_comp.append(np.linalg.norm(world.tip_pose_true()[:3, 3] - T[i, :3, 3]))
        world.command_q(qt[i])
        e_nom.append(np.linalg.norm(world.tip_pose_true()[:3, 3] - T[i, :3, 3]))
    e_comp, e_nom = np.array(e_comp), np.array(e_nom)
    assert np.all(e_comp <= 3 * sigma), np.round(e_comp / sigma, 2)
    assert np.sqrt(np.mean(e_comp ** 2)) < 0.1 * np.sqrt(np.mean(e_nom ** 2)), (e_comp, e_nom)
