"""The socketcand hub: python-can's real ``socketcand`` client against it, in-process and as the
``station mock canopen`` process."""

from __future__ import annotations

import re
import signal
import socket
import time
import uuid
from pathlib import Path

import can
import numpy as np
import pytest
from clirunner import station_proc, station_spawn
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.canopen.hub import SocketcandHub
from station.mocks.world import World

from station.robot import BusError, ConnectionLost, open_robot

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def hub_rig():
    chan = f"s-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=5)
    emu = CanopenEmulator(world, channel=chan).start()
    hub = SocketcandHub(chan, port=0).start()
    yield world, emu, hub
    hub.stop()
    emu.stop()


def url_of(hub: SocketcandHub, extra: str = "") -> str:
    return f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6{extra}"


def test_handshake_ok_arrives_alone_while_the_bus_is_busy(hub_rig):
    """python-can compares each handshake reply of one recv() exactly: no frame may follow the rawmode
    ok in the same read, even with heartbeats flowing."""
    world, emu, hub = hub_rig
    for d in emu.drives.values():  # busy bus: 6 heartbeats every 10 ms
        d.node.sdo[0x1017].raw = 10
        d.after_write(0x1017, 0)
    time.sleep(0.05)
    with socket.create_connection(("127.0.0.1", hub.port), timeout=2) as s:
        assert s.recv(256) == b"< hi >"
        s.sendall(b"< open can0 >")
        assert s.recv(256) == b"< ok >"
        s.sendall(b"< rawmode >")
        assert s.recv(256) == b"< ok >"
        s.sendall(b"< send 000 2 81 3 >")  # NMT reset node 3 from the raw client
        bootup, beat = rb"< frame 703 \d+\.\d{6} 00 >", rb"< frame 70[1-6] \d+\.\d{6} 7F >"
        buf = b""
        end = time.monotonic() + 1.0
        while not (re.search(bootup, buf) and re.search(beat, buf)) and time.monotonic() < end:
            buf += s.recv(4096)
        assert re.search(bootup, buf)  # boot-up of node 3 after the reset sent by this client
        assert re.search(beat, buf)  # heartbeats of the others


def test_wrong_bus_name_is_refused(hub_rig):
    world, emu, hub = hub_rig
    with pytest.raises(can.CanError):
        can.Bus(interface="socketcand", host="127.0.0.1", port=hub.port, channel="vcan9")


def test_robot_over_python_can_socketcand_streams_without_sdo(hub_rig):
    world, emu, hub = hub_rig
    robot = open_robot(url_of(hub))
    try:
        snap = robot.joint_positions()
        half = np.array([0.5 / (j.encoder.counts_per_unit * j.encoder.gear) for j in world.nominal.joints])
        assert np.all(np.abs(snap.q - world.encoder_q()) <= half + 1e-12)
        sniff = can.Bus(interface="virtual", channel=emu.channel)
        try:
            for _ in range(20):
                robot.joint_positions()
            frames = []
            while (m := sniff.recv(0)) is not None:
                frames.append(m)
        finally:
            sniff.shutdown()
        assert not [m for m in frames if 0x580 <= m.arbitration_id < 0x680]  # 0 SDOs in streaming
        assert sum(m.arbitration_id == 0x80 for m in frames) >= 20
        robot.enable()
        target = snap.q + 0.05
        robot.move_joints(target, speed=0.5)
        assert np.all(np.abs(world.encoder_q() - target) <= half + 1e-12)
    finally:
        robot.close()


def test_hub_forwards_no_error_frame_by_default(hub_rig):
    """socketcand's raw mode opens its CAN socket without CAN_RAW_ERR_FILTER unless started with -e (linux-can/
    socketcand src/state_raw.c): a bus-off on the daemon's side reaches no client. The station keeps streaming
    (no BusError out of nowhere); the hub counts what it dropped."""
    world, emu, hub = hub_rig
    robot = open_robot(url_of(hub))
    try:
        emu.inject_error_frame("busoff")  # crosses the virtual bus to the hub, which drops it
        hub.inject_error(0x40)  # the daemon's own controller reports bus-off: dropped too
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            robot.joint_positions()
        assert robot.faults.error is None and robot.bus._watch.error_frames == 0
        assert hub.errors_dropped == 2
    finally:
        robot.close()


def test_hub_with_an_error_mask_forwards_bus_off_like_socketcand_e(hub_rig):
    """``socketcand -e 0x1FFFFFFF`` (the hub's ``error_mask``): error frames of those classes are forwarded as
    ``< error CLASS ... >``, and the driver's bus-off watch latches BusError."""
    world, emu, _ = hub_rig
    hub = SocketcandHub(emu.channel, port=0, error_mask=0x1FFFFFFF).start()
    robot = open_robot(url_of(hub))
    try:
        emu.inject_error_frame("busoff")
        end = time.monotonic() + 1.0
        with pytest.raises(BusError, match="bus-off"):
            while time.monotonic() < end:
                robot.joint_positions()
    finally:
        robot.close()
        hub.stop()


def test_hub_gone_is_connection_lost(hub_rig):
    world, emu, hub = hub_rig
    robot = open_robot(url_of(hub, "&heartbeat_ms=50"))
    try:
        hub.drop_clients()
        end = time.monotonic() + 2.0
        with pytest.raises(ConnectionLost):
            while time.monotonic() < end:
                robot.joint_positions()
        end = time.monotonic() + 1.0
        while time.monotonic() < end and not any("closed the connection" in f for f in robot.status().faults):
            time.sleep(0.02)
        assert any("closed the connection" in f for f in robot.status().faults)
        assert robot.bus.network.notifier._stopped  # no receive thread left spinning on the dead socket
    finally:
        robot.close()


def test_station_mock_canopen_process():
    with station_spawn("mock", "canopen", "--port", "0", "--nodes", "1-6", cwd=ROOT,
                       env={"PYTHONUNBUFFERED": "1"}) as proc:
        line = proc.readline(timeout=60)
        m = re.match(r"socketcand 127\.0\.0\.1:(\d+) channel can0 url (\S+)$", line.strip())
        assert m, line + proc.wait().err if not proc.running() else line
        robot = open_robot(m.group(2))
        try:
            q0 = robot.joint_positions().q
            robot.enable()
            robot.move_joints(q0 + 0.02, speed=0.5)
            assert np.allclose(robot.joint_positions().q, q0 + 0.02, atol=1e-6)
            assert robot.identity().model == "arm6"
        finally:
            robot.close()
        proc.send_signal(signal.SIGTERM)
        r = proc.wait(10)
        assert r.code == 0, r.err


def test_station_mock_canopen_bad_input_exits_2(tmp_path):
    for args, what in ((["--nodes", "1-3"], "one node per joint"),
                       (["--world", str(tmp_path / "missing.yaml")], "missing.yaml")):
        out = station_proc("mock", "canopen", "--port", "0", *args, timeout=60, cwd=ROOT)
        assert out.code == 2 and out.err.startswith("station: error: ") and what in out.err
