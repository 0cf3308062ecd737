"""Measuring instruments as plugs (station.instruments): the laser tracker opens by URL through the
``station.instruments`` entry points, shares the close-once lifecycle and URL options of every instrument, and a
session's instruments are opened by ``s.instrument(option)``, read by ``s.measure_pose`` (6-DoF sample journaled
with the joints) and closed by the runner's teardown whatever ends the session. Real loopback sockets, the
tracker emulator on the simulated world, a hexapod on the CANopen emulator."""

import socket
import time

import numpy as np
import pytest
from station.mocks.launch import launch
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World

import station
from station.engine import read_journal
from station.engine.plan import PlannedPose
from station.instruments import InstrumentBase, PoseInstrument, PoseReading, open_instrument, schemes, url_examples
from station.kinematics import se3
from station.robot.errors import ConfigError, ConnectionLost

SERIAL = "HX-0007"
SLACK = "&sdo_timeout_ms=2000&heartbeat_ms=1000"  # the emulator shares this process (and a busy CI host)


@pytest.fixture
def world():
    return World.default("hexapod", seed=3)


def _connections(port: int) -> int:
    """Established TCP connections to ``port`` on loopback (the server side), from /proc/net/tcp."""
    n = 0
    with open("/proc/net/tcp") as f:
        lines = f.read().splitlines()[1:]
    for line in lines:
        local, state = line.split()[1], line.split()[3]
        if int(local.split(":")[1], 16) == port and state == "01":
            n += 1
    return n


def _wait_closed(port: int, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if _connections(port) == 0:
            return True
        time.sleep(0.02)
    return False


def test_tracker_is_an_instrument_plug(world):
    cfg = tracker_config({"noise": False})
    assert "tcp" in schemes() and url_examples() == "tcp://HOST:PORT"
    with TrackerServer(world, cfg) as trk:
        inst = open_instrument(f"{trk.url}?timeout_ms=1500&settle_ms=100")
        assert isinstance(inst, InstrumentBase) and isinstance(inst, PoseInstrument)
        assert (inst.timeout, inst.settle_timeout) == (1.5, 0.1)
        ident = inst.identity()
        assert (ident.serial, ident.model, ident.kind) == (cfg.serial, cfg.model, "tracker")
        assert float(ident.spec["sigma0_m"]) == 15e-6
        r = inst.measure()
        assert isinstance(r, PoseReading)
        truth = se3.invert(cfg.tracker_in_base) @ world.tip_pose_true()  # the world's true tool pose, tracker frame
        assert np.allclose(r.xyz, truth[:3, 3], atol=1e-8)
        assert _connections(trk.port) == 1
        with inst:
            pass
        assert inst.closed and _wait_closed(trk.port)
        inst.close()  # close-once: a second close is nothing
        with pytest.raises(ConnectionLost, match="is closed"):
            inst.measure()


def test_instrument_urls_are_checked_in_one_line(world):
    with pytest.raises(ConfigError, match=r"^instrument URL 'udp://x:1': unknown scheme 'udp'; known: tcp$"):
        open_instrument("udp://x:1")
    with pytest.raises(ConfigError, match=r"instrument URL .*unknown option\(s\) speed; known: settle_ms, timeout_ms"):
        open_instrument("tcp://127.0.0.1:9?speed=3")
    with pytest.raises(ConfigError, match=r"timeout_ms='0' is not a valid value \(expected number in \[1, 60000\] ms"):
        open_instrument("tcp://127.0.0.1:9?timeout_ms=0")
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectionLost, match="cannot connect"):
        open_instrument(f"tcp://127.0.0.1:{port}")


def _pose(world, index: int) -> PlannedPose:
    q = (world.nominal.home_q + 0.002 * index).tolist()
    return PlannedPose(index, "T", q, q)


def test_session_opens_measures_and_the_teardown_closes(tmp_path, monkeypatch, world):
    """``s.instrument("tracker")`` journals the instrument's identity, ``s.measure_pose`` journals a 6-DoF sample
    with the joints; an error in the middle of the session still closes the tracker (the runner's teardown)."""
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    cfg = tracker_config({"noise": False})
    with launch("canopen", world, serial=SERIAL) as emu, TrackerServer(world, cfg) as trk:
        kept = {}
        with pytest.raises(RuntimeError, match="the script failed"), \
                station.session(emu.url + SLACK, SERIAL, options={"tracker": trk.url}, db=f"sqlite:///{tmp_path}/r.db",
                                report=False) as s:
            tracker = s.instrument("tracker")
            assert s.instrument("tracker") is tracker  # one per session
            for i in range(2):
                pose = _pose(world, i)
                s.move_to(pose.q)
                kept[i] = s.measure_pose(pose)
            assert _connections(trk.port) == 1
            raise RuntimeError("the script failed")
        assert tracker.closed and _wait_closed(trk.port)
        folder = s.outcome.folder
    _, events = read_journal(folder / "journal.jsonl")
    inst = [e.data for e in events if e.type == "instrument"]
    assert inst == [{"option": "tracker", "url": trk.url, "serial": cfg.serial, "model": cfg.model,
                     "kind": "tracker", "protocol": "station-tracker/1", "spec": tracker.identity().spec}]
    samples = [e for e in events if e.type == "sample"]
    assert [smp.pose for smp in samples] == [0, 1] and all(smp.status["instrument"] == cfg.serial for smp in samples)
    for smp in samples:  # the reading journaled is the world's true tool pose at the joints journaled with it
        T = se3.invert(cfg.tracker_in_base) @ world.truth.fk_solve(np.array([smp.q]), guess=world.nominal.fk(
            np.array([smp.q]))).T[0]
        assert np.allclose(smp.measured, T[:3, 3], atol=1e-6)
        assert np.allclose(se3.rotvec_to_matrix(np.array(smp.measured_rotation)), T[:3, :3], atol=1e-6)
    assert any(e.type == "fault" for e in events) and events[-1].type == "end"


def test_session_without_the_instrument_option_says_what_is_missing(tmp_path, monkeypatch, world):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    with launch("canopen", world, serial=SERIAL) as emu, pytest.raises(ConfigError) as e, \
            station.session(emu.url + SLACK, SERIAL, name="probe", db=f"sqlite:///{tmp_path}/r.db", report=False) as s:
        s.instrument("tracker")
    assert str(e.value) == "probe needs a measuring instrument: --tracker tcp://HOST:PORT"
