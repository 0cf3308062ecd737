"""The UR emulator as the unmodified ur_rtde client sees it: RTDE recipes, the control-script handshake,
protective-stop semantics, the dashboard server, and the ``station mock ur`` command line."""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest
import rtde_control
import rtde_receive
import yaml
from clirunner import station_proc
from station.mocks.launch import dashboard, launch
from station.mocks.world import World, default_doc


@pytest.fixture
def emu(tmp_path):
    doc = default_doc("ur5e", seed=11)
    doc["motion"]["time_mode"] = "sim"
    doc["buses"] = {"ur": {"serial": "20235577777", "contact_bit": 17}}
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    with launch("ur", path) as e:
        e.world = World.from_file(path)
        yield e


def _rtde(host: str, kind: str, payload: bytes = b"") -> tuple[int, bytes]:
    """One raw RTDE request/reply on a fresh socket (protocol level, no ur_rtde)."""
    with socket.create_connection((host, 30004), timeout=3) as s:
        s.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)
        size, typ = struct.unpack(">HB", s.recv(3))
        body = b""
        while len(body) < size - 3:
            body += s.recv(size - 3 - len(body))
        return typ, body


def test_rtde_protocol_handshake_and_unknown_variables(emu):
    typ, body = _rtde(emu.host, "V", struct.pack(">H", 2))
    assert (chr(typ), body) == ("V", b"\x01")
    typ, body = _rtde(emu.host, "v")
    assert struct.unpack(">IIII", body)[:2] == (5, 11)  # PolyScope 5.x: ur_rtde chooses 500 Hz
    # trailing comma as ur_rtde 1.6.5 sends it; unknown names answered NOT_FOUND
    with socket.create_connection((emu.host, 30004), timeout=3) as s:
        s.sendall(struct.pack(">HB", 3 + 2, ord("V")) + struct.pack(">H", 2))
        s.recv(4)
        names = b"timestamp,actual_q,bogus_thing,"
        s.sendall(struct.pack(">HBd", 3 + 8 + len(names), ord("O"), 500.0) + names)
        size, typ = struct.unpack(">HB", s.recv(3))
        reply = s.recv(size - 3)
        assert reply[0] == 0 and reply[1:] == b"DOUBLE,VECTOR6D,NOT_FOUND"
    with pytest.raises(RuntimeError, match="not found"):
        rtde_receive.RTDEReceiveInterface(emu.host, -1.0, ["actual_q", "bogus_thing"])


def test_ur_rtde_streams_500hz_with_truth_and_contact_bit(emu):
    r = rtde_receive.RTDEReceiveInterface(emu.host)  # ur_rtde's full default recipe must be accepted
    try:
        np.testing.assert_array_equal(r.getActualQ(), emu.world.encoder_q())
        t0, w0 = r.getTimestamp(), time.monotonic()
        time.sleep(0.5)
        dt_ctrl, dt_wall = r.getTimestamp() - t0, time.monotonic() - w0
        assert abs(dt_ctrl - dt_wall) < 0.15  # the controller clock runs at wall speed (2 ms cycle)
        # a controller boots with the arm powered off (robot_mode 3 POWER_OFF), safety normal, no program
        assert r.getRobotMode() == 3 and r.getSafetyMode() == 1 and r.getRuntimeState() == 1
        assert list(r.getJointMode()) == [239] * 6  # JOINT_POWER_OFF_MODE
        assert r.getActualDigitalInputBits() == 0  # not touching: contact bit (17 here) clear
    finally:
        r.disconnect()


def _links_truth(world):
    """The arm as its factory calibration knows it (buses.ur.calibration default ``links``): the world's truth
    without the joint zero errors, the mounting and the tool (flange pose)."""
    keep = {n: world.nominal.param(n) for n in world.truth.param_names if n.startswith(("offset.", "base.", "tcp."))}
    return world.truth.with_params({**keep, **{f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")}})


def power_up(host: str) -> None:
    assert dashboard(host, "power on") == "Powering on"
    deadline = time.monotonic() + 10
    while dashboard(host, "robotmode") != "Robotmode: IDLE" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert dashboard(host, "brake release") == "Brake releasing"
    while dashboard(host, "robotmode") != "Robotmode: RUNNING" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert dashboard(host, "robotmode") == "Robotmode: RUNNING"


def test_control_script_handshake_protective_stop_and_unlock(emu):
    r = rtde_receive.RTDEReceiveInterface(emu.host)
    power_up(emu.host)
    c = rtde_control.RTDEControlInterface(emu.host)  # dashboard + script upload + PLAYING within 5 s
    try:
        assert c.isProgramRunning() and r.getRuntimeState() == 2
        q0 = np.array(r.getActualQ())
        assert c.moveJ((q0 + 0.05).tolist(), 1.0, 1.4)  # sync: returns after the script's "done"
        time.sleep(0.01)  # the receive connection may be a package behind the control connection
        np.testing.assert_allclose(r.getActualQ(), q0 + 0.05, atol=1e-9)
        c.setTcp([0, 0, 0.1, 0, 0, 0])
        np.testing.assert_allclose(c.getTCPOffset(), [0, 0, 0.1, 0, 0, 0], atol=1e-12)
        pose = np.array(r.getActualTCPPose())
        T = _links_truth(emu.world).fk(q0 + 0.05)  # the controller's own (calibrated) kinematics + TCP
        np.testing.assert_allclose(pose[:3], T[:3, 3] + T[:3, 2] * 0.1, atol=1e-9)
        assert "protective stop" in dashboard(emu.host, "emulator protective_stop")
        time.sleep(0.05)
        assert r.isProtectiveStopped() and r.getSafetyMode() == 3 and r.getSafetyStatusBits() & (1 << 2)
        assert not c.isProgramRunning() and r.getRuntimeState() == 4  # program paused
        assert not c.moveJ(q0.tolist(), 1.0, 1.4)  # commands fail during a protective stop
        np.testing.assert_allclose(r.getActualQ(), q0 + 0.05, atol=1e-9)
        assert dashboard(emu.host, "unlock protective stop").startswith("Cannot unlock protective stop until 5s")
        time.sleep(5.0)
        assert dashboard(emu.host, "unlock protective stop") == "Protective stop releasing"
        time.sleep(0.05)  # a few 2 ms packages
        assert not r.isProtectiveStopped() and r.getSafetyStatusBits() & 1
        assert c.reuploadScript()
        deadline = time.monotonic() + 5
        while not c.isProgramRunning() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert c.moveJ(q0.tolist(), 1.0, 1.4)
        time.sleep(0.01)
        np.testing.assert_allclose(r.getActualQ(), q0, atol=1e-9)
        c.stopScript()  # returns once the CONTROL connection sees the program stopped
        deadline = time.monotonic() + 0.5  # the receive connection may be packages behind (seen in CI: 2)
        while r.getRuntimeState() != 1 and time.monotonic() < deadline:
            time.sleep(0.002)
        assert r.getRuntimeState() == 1
    finally:
        c.disconnect()
        r.disconnect()


def test_dashboard_answers_like_polyscope(emu):
    assert dashboard(emu.host, "PolyscopeVersion").startswith("URSoftware 5.11")
    assert dashboard(emu.host, "get serial number") == "20235577777"
    assert dashboard(emu.host, "get robot model") == "UR5"
    assert dashboard(emu.host, "is in remote control") == "true"
    assert dashboard(emu.host, "safetystatus") == "Safetystatus: NORMAL"
    assert dashboard(emu.host, "no such thing").startswith("could not understand")
    tip = np.array([float(x) for x in dashboard(emu.host, "emulator tip").split()[1:]])
    np.testing.assert_allclose(tip, emu.world.tip_true(), atol=1e-9)  # emulator-only truth read-back


def test_cli_rejects_bad_host_and_bad_world(tmp_path):
    out = station_proc("mock", "ur", "--host", "not-an-ip", timeout=30)
    assert out.code == 2 and "station: error:" in out.err and "not-an-ip" in out.err
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: station-world/1\nunits: {length: m, angle: rad}\nrobot: {model: ur5e}\n"
                   "motion: {time_mode: warp}\n")
    out = station_proc("mock", "ur", "--host", "127.0.0.1", "--world", bad, timeout=30)
    assert out.code == 2 and "station: error:" in out.err and "time_mode" in out.err
