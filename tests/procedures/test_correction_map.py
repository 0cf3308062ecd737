"""correction_map end to end: a hexapod of six CiA 402 linear drives on the CANopen emulator (real canopen library
on a python-can virtual bus), the laser-tracker emulator on a loopback TCP socket, the procedure through the
engine; the truth comes from the simulated world. Also: a resume after an interruption measures no pose twice."""

import json
import signal

import numpy as np
import pytest
from clirunner import station_proc, station_spawn
from station.mocks.launch import launch
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World

from station.api import resume
from station.api import run as start
from station.engine import read_journal
from station.kinematics import se3
from station.records import open_records
from station.solver.map import CorrectionMap

SIGMA_0, SIGMA_PER_M = 15e-6, 6e-6  # the tracker's specification (docs/hardware.md), 1 sigma per reflector, axis
SERIAL = "HX-0042"


@pytest.fixture
def cell(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world = World.default("hexapod", seed=7)
    cfg = tracker_config({})
    with launch("canopen", world, serial=SERIAL) as emu, TrackerServer(world, cfg, seed=11) as trk:
        yield world, cfg, emu, trk, f"sqlite:///{tmp_path / 'records.db'}"


@pytest.fixture(scope="module")
def resumed(tmp_path_factory):
    """ONE hexapod session for the two tests below (a session of 76 configurations is most of their time): Ctrl-C
    after 25 configurations, then resumed to completion on the same robot and tracker. What each test asserts is
    its own; the uninterrupted start-to-PASS path runs in test_command_line_over_socketcand_and_tcp."""
    tmp = tmp_path_factory.mktemp("resumed")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("STATION_HOME", str(tmp / "home"))
        world = World.default("hexapod", seed=7)
        cfg = tracker_config({})
        db = f"sqlite:///{tmp / 'records.db'}"
        with launch("canopen", world, serial=SERIAL) as emu, TrackerServer(world, cfg, seed=11) as trk:

            def progress(done, total, text):
                if done >= 25:
                    raise KeyboardInterrupt  # the operator's Ctrl-C after 25 configurations

            out = start("correction_map", emu.url, SERIAL, db=db, options={"tracker": trk.url, "grid": 1},
                        report=False, progress=progress)
            _, events = read_journal(out.folder / "journal.jsonl")
            first = {"events": events, "measured": trk.measurements}
            seen = {"n": 0}

            def count(done, total, text):
                seen["n"] = total

            again = resume(out.session, db=db, report=False, progress=count)
            yield {"world": world, "cfg": cfg, "db": db, "out": out, "first": first, "again": again,
                   "total": seen["n"], "measured": trk.measurements}


def test_map_from_tracker_beats_nominal_within_noise_bound(resumed):
    world, cfg, db, out = resumed["world"], resumed["cfg"], resumed["db"], resumed["again"]
    assert out.status == "completed", out.error
    assert out.passed and out.exit_code == 0 and out.stored
    plan_len = len(out.record["samples"])
    assert resumed["measured"] == plan_len  # one tracker reading per configuration, none repeated
    # the map as stored: in the session folder and in the record
    doc = json.loads((out.folder / "map.json").read_text())
    cmap = CorrectionMap.from_dict(doc)
    with open_records(db) as rec:
        stored = rec.session(out.session)
    assert stored["correction_map"]["map"]["format"] == "station-map/1"
    assert stored["correction_map"]["map"]["statistics"]["id"] == doc["statistics"]["id"]
    reg = se3.pose_to_matrix(np.array(stored["correction_map"]["registration"]["instrument_in_base"]))
    # ground truth: at each held-out reading, the TRUE tool pose of the world, seen from the tracker, vs what the
    # map (and the nominal model) predict there, seen from the tracker through the session's registration
    held = [s for s in out.record["samples"] if s["set"] == "holdout"]
    assert len(held) == 12
    x = np.array([s["q"] for s in held])
    nom = world.nominal
    true_t = se3.invert(cfg.tracker_in_base) @ world.truth.fk_solve(x, guess=nom.fk(x)).T
    mapped, _ = cmap.measure(nom, x)
    e_map = np.linalg.norm((se3.invert(reg) @ se3.pose_to_matrix(mapped))[:, :3, 3] - true_t[:, :3, 3], axis=1)
    e_nom = np.linalg.norm((se3.invert(reg) @ nom.fk(x))[:, :3, 3] - true_t[:, :3, 3], axis=1)
    rms_map, rms_nom = (float(np.sqrt(np.mean(e ** 2))) for e in (e_map, e_nom))
    # noise-derived bound: the 3-D RMS of ONE reflector reading at the farthest held-out distance; the map
    # averages many readings, so it must do better than a single one
    sigma = SIGMA_0 + SIGMA_PER_M * np.linalg.norm(true_t[:, :3, 3], axis=1).max()
    assert rms_map < np.sqrt(3) * sigma, (rms_map, sigma)
    assert rms_map < 0.3 * rms_nom, (rms_map, rms_nom)
    # what the procedure judged (against the noisy tracker) agrees with the truth-based numbers
    meas = {m["name"]: m for m in out.record["verdict"]["measurements"]}
    assert meas["holdout_rms"]["value"] * 1e-3 < np.sqrt(rms_map ** 2 + 3 * sigma ** 2)
    assert abs(meas["holdout_nominal_rms"]["value"] * 1e-3 - rms_nom) < 0.2 * rms_nom
    # calibrated control too: commands from the map bring the TRUE tool onto held-out targets
    targets = se3.matrix_to_pose(reg @ true_t, "rotvec")  # reachable poses, in the registered base frame
    c, x_nom = cmap.command(nom, targets, ("x", "y", "z", "rx", "ry", "rz"))
    got = reg @ se3.invert(cfg.tracker_in_base) @ world.truth.fk_solve(c, guess=nom.fk(c)).T
    got_nom = reg @ se3.invert(cfg.tracker_in_base) @ world.truth.fk_solve(x_nom, guess=nom.fk(x_nom)).T
    e_c = np.linalg.norm(got[:, :3, 3] - targets[:, :3], axis=1)
    e_c_nom = np.linalg.norm(got_nom[:, :3, 3] - targets[:, :3], axis=1)
    assert np.sqrt(np.mean(e_c ** 2)) < min(np.sqrt(3) * sigma, 0.3 * np.sqrt(np.mean(e_c_nom ** 2)))


def test_resume_after_interruption_measures_no_pose_twice(resumed):
    out = resumed["out"]
    assert out.status == "interrupted" and out.exit_code == 130
    first = [e for e in resumed["first"]["events"] if e.type == "sample"]
    assert len(first) == 25 and resumed["first"]["measured"] == 25

    again = resumed["again"]
    assert again.status == "completed", again.error
    assert again.passed
    _, events = read_journal(again.folder / "journal.jsonl")
    samples = [e for e in events if e.type == "sample"]
    poses = [s.pose for s in samples]
    assert len(poses) == len(set(poses)) == resumed["total"]  # every configuration once
    assert [s.seq for s in samples[:25]] == [s.seq for s in first]  # the first 25 kept as journaled
    assert resumed["measured"] == resumed["total"]  # the tracker measured no configuration twice
    assert len([e for e in events if e.type == "plan"]) == 1  # the same plan, not a new one


def test_without_or_with_a_dead_tracker_nothing_moves(cell):
    world, cfg, emu, trk, db = cell
    q0 = world.encoder_q().copy()
    out = start("correction_map", emu.url, SERIAL, db=db, options={"grid": 1}, report=False)
    assert out.status == "error" and out.exit_code == 2
    assert str(out.error) == "correction_map needs a measuring instrument: --tracker tcp://HOST:PORT"
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = start("correction_map", emu.url, SERIAL, db=db, options={"grid": 1, "tracker": f"tcp://127.0.0.1:{port}"},
                report=False)
    assert out.status == "error" and "cannot connect" in str(out.error) and "\n" not in str(out.error)
    assert np.array_equal(world.encoder_q(), q0)  # the robot did not move


def test_command_line_over_socketcand_and_tcp(tmp_path):
    """The documented commands: `station mock tracker --world W --canopen` (one process: drives + tracker), then
    `station run correction_map --robot URL --tracker URL` through python-can's socketcand interface."""
    from station.mocks.world.example import example_text

    world = tmp_path / "w.yaml"
    world.write_text(example_text("hexapod"))  # what `station mock world example --model hexapod` prints
    with station_spawn("mock", "tracker", "--world", world, "--canopen", module=True) as proc:
        trk = proc.readline().split()[3]
        robot = proc.readline().split()[5]
        r = station_proc("run", "correction_map", "--robot", robot, "--serial", "HX-9", "--tracker", trk, "--grid",
                         "1", "-q", "--db", f"sqlite:///{tmp_path / 'r.db'}", timeout=300,
                         env={"STATION_HOME": str(tmp_path / "home")})
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    assert r.code == 0, r.err
    lines = r.out.strip().splitlines()
    assert lines[-1] == "PASS" and any(line.split()[0] == "holdout_rms" for line in lines if line.strip())


def test_hexapod_legs_are_linear_cia402_drives(cell):
    """Six prismatic drives in counts per metre: what the driver reads is the world's leg length within one
    count, and a Cartesian jog of the platform moves the TRUE tool by about the step."""
    import station

    world, cfg, emu, trk, db = cell
    with station.connect(emu.url) as robot:
        robot.enable()
        target = world.nominal.home_q + np.array([1, -1, 2, -2, 1.5, 0.5]) * 1e-3
        robot.move_joints(target)
        snap = robot.joint_positions()
        per_m = 26214400  # hexapod.yaml: 5 mm lead ball screws, 17-bit motor encoders
        assert snap.raw_unit == "count"
        assert np.all(np.abs(np.array(snap.raw) - world.encoder_q() * per_m) <= 1.0)
        assert np.all(np.abs(snap.q - world.encoder_q()) <= 1.0 / per_m)
        before = world.tip_pose_true()[:3, 3]
        robot.jog("cartesian", 2, 0.002)  # +2 mm along z
        moved = world.tip_pose_true()[:3, 3] - before
        assert abs(moved[2] - 0.002) < 2e-4 and np.linalg.norm(moved[:2]) < 2e-4  # the truth differs slightly
