"""The controller's factory calibration on the interface a real UR serves it: the KinematicsInfo sub-package of the
robot state on the primary (30001) and secondary (30002) client interfaces. The emulator derives it from the
world's true arm; the station reads it, converts it to its model (re-intersecting nearly parallel axes) and uses
that as the session's nominal model, with the checksum in the journaled identity. Truth: the world file's model
and hidden errors, and a plain-DH product written here."""

from __future__ import annotations

import math
import socket
import struct

import numpy as np
import pytest
import yaml
from station.drivers.ur.primary import read_kinematics
from station.mocks.world import World, default_doc

from station.kinematics import load_model
from station.robot import open_robot

START = [0.1, -1.45, 1.6, -1.72, -1.5708, 0.2]


def _world(tmp_path, seed=9, **ur):
    doc = default_doc("ur5e", seed=seed)  # hidden random link errors, Hayati tilts of the parallel joints included
    doc["motion"].update(time_mode="sim", start=list(START))
    doc["buses"] = {"ur": {"serial": "20235500778", **ur}}
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path, World.from_file(path)


def _links_truth(world, tool: bool):
    """The arm as its factory knew it (buses.ur.calibration default ``links``): the true link geometry; joint
    zeros, mounting and tool nominal (the tool zero for the flange)."""
    keep = {n: world.nominal.param(n) for n in world.truth.param_names if n.startswith(("offset.", "base.", "tcp."))}
    if not tool:
        keep.update({f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")})
    return world.truth.with_params(keep)


def _plain_dh_fk(theta, a, d, alpha, q) -> np.ndarray:
    T = np.eye(4)
    for i in range(6):
        ct, st = math.cos(theta[i] + q[i]), math.sin(theta[i] + q[i])
        ca, sa = math.cos(alpha[i]), math.sin(alpha[i])
        T = T @ np.array([[ct, -st * ca, st * sa, a[i] * ct], [st, ct * ca, -ct * sa, a[i] * st],
                          [0, sa, ca, d[i]], [0, 0, 0, 1]])
    return T


def test_primary_and_secondary_serve_version_then_kinematics_info_of_the_true_arm(tmp_path, emulators):
    path, world = _world(tmp_path)
    emu = emulators("ur", path)
    with socket.create_connection((emu.host, 30001), timeout=3) as s, s.makefile("rb") as f:
        size, kind = struct.unpack(">iB", f.read(5))
        body = f.read(size - 5)
        assert kind == 20 and body[9] == 3 and b"URControl" in body  # the version message comes first
    infos = [read_kinematics(emu.host, port) for port in (30001, 30002)]
    assert infos[0] == infos[1] and infos[0].version.startswith("URControl 5.11")
    info = infos[0]
    # the published table plus the factory's deltas, as plain DH: a tilt between the parallel joints puts their
    # common normal hundreds of metres out (UR's ur_calibration documents 439 m on a real UR10)
    assert max(abs(v) for v in info.d) > 50.0 and max(abs(v) for v in info.theta[1:4]) > 0.3
    truth = _links_truth(world, tool=False)
    for q in np.random.default_rng(2).uniform(-3, 3, size=(30, 6)):
        np.testing.assert_allclose(_plain_dh_fk(info.theta, info.a, info.d, info.alpha, q)[:3, 3],
                                   truth.fk(q)[:3, 3], atol=1e-9)
    assert len(info.checksum) == 6 and info.calibration_status == 1


def test_the_session_model_is_the_controllers_calibration_with_its_checksum(tmp_path, emulators, monkeypatch):
    from station.engine.journal import read_journal
    from station.engine.runner import create_session

    path, world = _world(tmp_path)
    emu = emulators("ur", path)
    raw = read_kinematics(emu.host)
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    with open_robot(f"ur://{emu.host}") as robot:
        q = np.random.default_rng(3).uniform(-3, 3, size=(30, 6))
        np.testing.assert_allclose(robot.model.fk(q)[:, :3, 3], _links_truth(world, tool=True).fk(q)[:, :3, 3],
                                   atol=1e-9)
        # re-intersected: no compensating metres in the station's model
        assert max(abs(robot.model.param(n)) for n in robot.model.param_names if n.endswith((".d", ".a"))) < 1.0
        dev = robot.identity().devices[0]
        assert dev["calibration"] == "controller" and dev["calibration_checksum"] == raw.checksum_text
        s = create_session(robot, "20235500778", name="probe")
        s.journal.close()
        header, _ = read_journal(s.journal.path)
        assert header.robot["devices"][0]["calibration_checksum"] == raw.checksum_text
    with open_robot(f"ur://{emu.host}?calibration=none") as robot:  # the published table, on request
        np.testing.assert_allclose(robot.model.fk(q), load_model("ur5e").fk(q), atol=1e-12)
        assert robot.identity().devices[0]["calibration"] == "published table"


@pytest.mark.slow
def test_a_power_cycle_keeps_the_calibration_and_boots_powered_off(tmp_path, emulators):
    path, _ = _world(tmp_path)
    emu = emulators("ur", path)
    with open_robot(f"ur://{emu.host}?power_on=yes") as robot:
        robot.enable()
        before = robot.identity().devices[0]["calibration_checksum"]
        emu.dashboard("emulator power_cycle 0.3")
        robot.reconnect(timeout=10.0)  # the ports come back after the reboot
        assert robot.identity().devices[0]["calibration_checksum"] == before
        assert not robot.status().enabled and emu.dashboard("robotmode") == "Robotmode: POWER_OFF"
        robot.enable()
        q = robot.joint_positions().q
        robot.move_joints(q + 0.02, speed=1.0)
        np.testing.assert_allclose(robot.joint_positions().q, q + 0.02, atol=1e-9)


@pytest.mark.parametrize("calibration", ["arm", "none"])
def test_what_the_factory_knew_is_the_worlds_choice(tmp_path, calibration):
    """``buses.ur.calibration``: ``arm`` includes the hidden joint zeros, ``none`` is the published table."""
    from station.mocks.ur.factory import factory

    _, world = _world(tmp_path, calibration=calibration)
    f = factory(world, calibration)
    q = np.random.default_rng(4).uniform(-3, 3, size=(10, 6))
    if calibration == "none":
        want = world.nominal.with_params({f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")})
    else:
        keep = {n: world.nominal.param(n) for n in world.truth.param_names if n.startswith(("base.", "tcp."))}
        want = world.truth.with_params({**keep, **{f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")}})
    np.testing.assert_allclose(f.table.fk(q)[:, :3, 3], want.fk(q)[:, :3, 3], atol=1e-9)
