"""The emulated laser tracker (station mock tracker) and its client (station.drivers.tracker) on a real loopback
TCP socket: the documented line protocol, readings against the world's truth, noise within the instrument's
specification, bounded waits and one-line errors, and the CSV import of a tracker's export (station map build
--measurements)."""

import signal
import socket
import time

import numpy as np
import pytest
from clirunner import station_proc, station_spawn
from station.drivers.tracker import open_tracker
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World

from station.kinematics import se3
from station.robot.errors import ConfigError, ConnectionLost, DeviceFault
from station.solver.map import CorrectionMap, plan

SIGMA_0, SIGMA_PER_M = 15e-6, 6e-6  # the instrument's specification (docs/hardware.md), 1 sigma per reflector, axis
TRACKER = {"units": {"length": "mm", "angle": "deg"}, "pose": {"x": 2000, "y": 500, "z": 800, "rz": 120}}


def _truth_in_tracker(world, cfg):
    return se3.invert(cfg.tracker_in_base) @ world.tip_pose_true()


def _ask(port: int, *lines: str) -> list[str]:
    """Raw protocol, no client library: one request line, one answer line each."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s, s.makefile("rb") as f:
        out = []
        for line in lines:
            s.sendall(line.encode() + b"\n")
            out.append(f.readline().decode().strip())
        return out


@pytest.fixture
def hexapod():
    return World.default("hexapod", seed=2)


def test_protocol_lines_and_exact_reading(hexapod):
    cfg = tracker_config({**TRACKER, "noise": False})
    with TrackerServer(hexapod, cfg) as trk:
        ident, meas, bad, bye = _ask(trk.port, "ID", "MEASURE", "FOO", "QUIT")
    assert ident.split()[:3] == ["OK", "station-tracker/1", cfg.serial]
    assert f"model={cfg.model}" in ident.split()[3:]  # with the serial: the identity a resume checks
    assert bad.startswith("ERR unknown command") and bye == "OK bye"
    v = [float(x) for x in meas.split()[1:]]
    assert meas.startswith("OK ") and len(v) == 7
    T = _truth_in_tracker(hexapod, cfg)  # ground truth: the world's true tool pose, moved into the tracker frame
    assert np.allclose(v[:3], T[:3, 3], atol=1e-8)
    assert np.allclose(se3.rotvec_to_matrix(np.array(v[3:6])), T[:3, :3], atol=1e-8)


def test_noise_matches_the_specification(hexapod):
    cfg = tracker_config(TRACKER)
    T = _truth_in_tracker(hexapod, cfg)
    sigma = SIGMA_0 + SIGMA_PER_M * np.linalg.norm(T[:3, 3])  # per reflector and axis at this distance
    with TrackerServer(hexapod, cfg, seed=5) as trk, open_tracker(trk.url) as c:
        p = np.array([c.measure().xyz for _ in range(300)])
    err = p - T[:3, 3]
    std = err.std(axis=0)
    # the probe origin is a rigid fit of 3 reflectors: its noise is below one reflector's, but not far below
    assert np.all(std < sigma) and np.all(std > 0.3 * sigma), (std, sigma)
    assert np.all(np.abs(err.mean(axis=0)) < 4 * sigma / np.sqrt(len(p)))  # unbiased


def test_moving_target_waits_then_faults_in_one_line():
    w = World.default("hexapod", seed=1, time_mode="sim")
    with TrackerServer(w, tracker_config({})) as trk:
        w.command_q(w.nominal.home_q + 0.01)
        assert _ask(trk.port, "MEASURE")[0].startswith("ERR moving")
        c = open_tracker(trk.url, settle_timeout=0.3)
        t0 = time.monotonic()
        with pytest.raises(DeviceFault, match=r"moving") as e:
            c.measure()
        assert time.monotonic() - t0 < 2 and "\n" not in str(e.value)
        w.advance(5.0)  # the move ends: a stationary reading now
        assert np.isfinite(c.measure().xyz).all()
        c.close()
        c.close()  # close-once


def test_faults_are_bounded_and_one_line(hexapod):
    with TrackerServer(hexapod, tracker_config({})) as trk:
        c = open_tracker(trk.url, timeout=0.5)
        hexapod.faults.inject("device_fault", "tracker")
        with pytest.raises(DeviceFault, match="beam"):
            c.measure()
        hexapod.faults.inject("timeout", "tracker")
        t0 = time.monotonic()
        with pytest.raises(ConnectionLost, match=r"no answer within 0.5 s"):
            c.measure()
        assert time.monotonic() - t0 < 2
        c.close()
        c = open_tracker(trk.url, timeout=0.5)
        hexapod.faults.inject("disconnect", "tracker")
        with pytest.raises(ConnectionLost, match="closed the connection"):
            c.measure()
        c.close()
    with pytest.raises(ConfigError, match="expected tcp://HOST:PORT"):
        open_tracker("udp://127.0.0.1")
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectionLost, match="cannot connect"):
        open_tracker(f"tcp://127.0.0.1:{port}", timeout=0.5)


def test_station_mock_tracker_process(tmp_path):
    world = tmp_path / "w.yaml"
    r = station_proc("mock", "world", "example", "--model", "hexapod")
    assert r.code == 0, r.err
    text = r.out.replace("buses:", "buses:\n  tracker: {serial: LT-42}", 1)
    world.write_text(text)
    with station_spawn("mock", "tracker", "--world", world, module=True) as proc:
        line = proc.readline().split()
        assert line[0] == "tracker" and line[3].startswith("tcp://127.0.0.1:") and line[5] == "LT-42"
        with open_tracker(line[3]) as c:
            assert c.serial == "LT-42"
            assert np.isfinite(c.measure().pose).all()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("{serial: LT-42}", "{pose: {x: 1}}"))
    r = station_proc("mock", "tracker", "--world", bad, timeout=60)
    assert r.code == 2 and r.err_lines == [
        "station: error: buses.tracker.units: state the units of pose and reflectors ({length: mm, angle: deg})"]


def test_csv_import_of_a_tracker_export(tmp_path, hexapod):
    """A tracker's export in its own frame (mm, deg) -> registered map; held-out readings corrected by the map
    match the world's truth far better than the nominal model."""
    from station.mocks.world.tracker import measure_poses

    cfg = tracker_config({**TRACKER, "noise": False})
    nom, truth = hexapod.nominal, hexapod.truth
    p = plan(nom, 1, mesh="simplex")
    T = truth.fk_solve(p.x, guess=nom.fk(p.x)).T
    M = measure_poses(T, cfg.reflectors, cfg.tracker_in_base, np.random.default_rng(1))  # real noise
    v = se3.matrix_to_pose(M, "rotvec")
    np.savetxt(tmp_path / "x.csv", p.x * 1e3, delimiter=",", comments="",
               header="x1[mm],x2[mm],x3[mm],x4[mm],x5[mm],x6[mm]")
    np.savetxt(tmp_path / "tracker.csv", np.column_stack([v[:, :3] * 1e3, np.degrees(v[:, 3:])]), delimiter=",",
               header="# tracker export, instrument frame\nx[mm],y[mm],z[mm],rx[deg],ry[deg],rz[deg]", comments="")
    r = station_proc("map", "build", "--model", "hexapod", "--samples", tmp_path / "x.csv", "--measurements",
                     tmp_path / "tracker.csv", "--mesh", "simplex", "--out", tmp_path / "map.json")
    assert r.code == 0, r.err
    import json

    doc = json.loads((tmp_path / "map.json").read_text())
    cmap = CorrectionMap.from_dict(doc)
    reg = se3.pose_to_matrix(np.array(doc["statistics"]["registration"]["instrument_in_base"]))
    # held-out: random readings; what the map predicts, seen from the tracker, vs the true pose seen from it
    rng = np.random.default_rng(3)
    lo, hi = p.levels[0][0], p.levels[0][-1]
    xh = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (40, 6))
    xh = xh[nom.fk_solve(xh).ok]
    true_t = se3.invert(cfg.tracker_in_base) @ truth.fk_solve(xh, guess=nom.fk(xh)).T
    mapped, _ = cmap.measure(nom, xh)
    e_map = np.linalg.norm((se3.invert(reg) @ se3.pose_to_matrix(mapped))[:, :3, 3] - true_t[:, :3, 3], axis=1)
    e_nom = np.linalg.norm((se3.invert(reg) @ nom.fk(xh))[:, :3, 3] - true_t[:, :3, 3], axis=1)
    sigma = SIGMA_0 + SIGMA_PER_M * np.linalg.norm(true_t[:, :3, 3], axis=1).max()
    rms = float(np.sqrt(np.mean(e_map ** 2)))
    assert rms < np.sqrt(3) * sigma, (rms, sigma)  # below one reflector's 3-D noise
    assert rms < 0.3 * np.sqrt(np.mean(e_nom ** 2))
    # a wrong row count is one line, exit 2, nothing written
    (tmp_path / "short.csv").write_text("\n".join((tmp_path / "tracker.csv").read_text().splitlines()[:10]) + "\n")
    r = station_proc("map", "build", "--model", "hexapod", "--samples", tmp_path / "x.csv", "--measurements",
                     tmp_path / "short.csv", "--mesh", "simplex", "--out", tmp_path / "map2.json")
    assert r.code == 2 and len(r.err_lines) == 1 and "one row per sample" in r.err
    assert not (tmp_path / "map2.json").exists()
