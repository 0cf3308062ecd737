"""DynamixelRobot through the real dynamixel_sdk over a pty to the emulator serving a simulated world."""

from __future__ import annotations

import time

import numpy as np
import pytest
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.world import World

from station.robot import ConfigError, DeviceFault, LimitError, Robot, open_robot

IDS = [11, 12, 13, 14]


def _tick(world, j):  # one encoder tick of joint j, SI
    return 1.0 / (world.nominal.joints[j].encoder.counts_per_unit * world.nominal.joints[j].encoder.gear)


def to_write_pose(robot, values) -> None:
    """What the station's write-back does before ``write_calibration`` (station.engine.writeback.to_write_pose),
    without a cell to check against: the homing offset is EEPROM, written with the torque off, and a DYNAMIXEL
    has no brake, so the arm goes where the joints to be written carry no gravity torque."""
    for _ in range(40):
        q = robot.write_pose(values)
        if q is None:
            return
        robot.move_joints(q)
    raise AssertionError("no write pose within 40 moves")


@pytest.fixture()
def rig(robot_rig):
    """omx servos 11-14 and the contact sensor 200 at 1 Mbps on a pty, the driver connected (not enabled)."""
    world = World.default(model="omx", seed=7, start=[0.2, -0.3, 0.4, 0.1])
    emu, robot = robot_rig("dynamixel", world, ids=IDS, query="&latency=50", enable=False)
    assert "contact=200" in emu.url
    return world, emu, robot


def test_open_identity_and_protocol(rig):
    world, emu, robot = rig
    assert isinstance(robot, Robot)
    ident = robot.identity()
    assert ident.vendor == "ROBOTIS" and ident.model == "omx" and ident.firmware == "46"
    assert ident.serial == "DXL-OMX-11.12.13.14"  # deterministic from the ids when the URL has no serial=
    assert [d["id"] for d in ident.devices] == [*IDS, 200]
    assert [d["model_number"] for d in ident.devices][:4] == [1020] * 4


def test_readout_equals_hidden_truth_through_the_conversion_chain(rig):
    world, emu, robot = rig
    robot.enable()
    rng = np.random.default_rng(5)
    lo, hi = world.nominal.lower, world.nominal.upper
    # non-zero homing offsets, so the device-side correction is part of the chain
    to_write_pose(robot, {"offset.j1": 0.05, "offset.j3": -0.02})
    robot.write_calibration({"offset.j1": 0.05, "offset.j3": -0.02})
    cal = robot.read_calibration()
    offs = np.array([cal[f"offset.j{k + 1}"] for k in range(4)])
    for _ in range(5):
        robot.move_joints(rng.uniform(lo + 0.2, hi - 0.2))
        snap = robot.joint_positions()
        truth = world.encoder_q() + offs  # device reports q_raw + offset
        half_tick = np.array([_tick(world, j) for j in range(4)]) / 2
        assert np.all(np.abs(snap.q - truth) <= half_tick + 1e-12)
        assert snap.raw_unit == "tick" and len(snap.raw) == 4


def test_motion_reaches_targets_and_one_sync_read_per_snapshot(rig):
    world, emu, robot = rig
    robot.enable()
    target = np.array([0.5, 0.2, -0.3, 0.6])
    robot.move_joints(target, speed=1.0)
    tick = np.array([_tick(world, j) for j in range(4)])
    assert np.all(np.abs(world.encoder_q() - target) <= tick / 2 + 1e-12)
    robot.joint_positions()  # round trip: earlier unanswered sync writes have been counted
    emu.reset_stats()
    robot.joint_positions()
    # one Fast Sync Read: 14 + 4 B request, 8 + 4 x 8 B answer
    assert emu.stats["by_inst"] == {"fast_sync_read": 1}
    assert (emu.stats["bytes_in"], emu.stats["bytes_out"]) == (18, 40)


def test_plain_sync_read_snapshot_costs_one_transaction(rig):
    world, emu, _ = rig
    with open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&fast=0&latency=50") as robot:
        emu.reset_stats()
        snap = robot.joint_positions()
        assert emu.stats["by_inst"] == {"sync_read": 1}
        assert (emu.stats["bytes_in"], emu.stats["bytes_out"]) == (18, 4 * 15)
        assert np.all(np.abs(snap.q - world.encoder_q()) <= _tick(world, 0) / 2 + 1e-12)


def test_profile_velocity_is_respected_in_real_time(robot_rig):
    world = World.default(model="omx", time_mode="realtime")
    _, robot = robot_rig("dynamixel", world, ids=IDS, query="&latency=50")
    t0 = time.monotonic()
    robot.move_joints(np.array([0.4, 0.0, 0.0, 0.0]), speed=1.0)
    dt = time.monotonic() - t0
    # 0.4 rad at <= 1 rad/s (profile velocity quantised down) plus the acceleration ramps
    assert 0.4 <= dt < 1.5
    assert abs(world.encoder_q()[0] - 0.4) <= _tick(world, 0)


def test_limits_refuse_and_nothing_is_sent(rig):
    world, emu, robot = rig
    robot.enable()
    emu.reset_stats()
    before = world.encoder_q()
    for bad in ([3.0, 0, 0, 0], [0, 0, np.nan, 0], [0, 0, 0]):
        with pytest.raises(LimitError):
            robot.move_joints(np.array(bad))
    with pytest.raises(LimitError, match="outside its limits"):
        robot.jog("joint", 1, 5.0)
    assert "sync_write" not in emu.stats["by_inst"]
    assert np.array_equal(world.encoder_q(), before)


def test_jog_joint_and_cartesian_with_tool_speed_cap(rig):
    world, emu, robot = rig
    robot.enable()
    q0 = robot.joint_positions().q
    robot.jog("joint", 2, 0.1)
    assert abs(robot.joint_positions().q[2] - (q0[2] + 0.1)) <= _tick(world, 2)
    q1 = robot.joint_positions().q
    p0 = world.nominal.position(q1)
    with pytest.raises(LimitError, match="speed"):
        robot.jog("cartesian", 2, 0.01, speed=5.0)  # above the 0.25 m/s manual cap: refused, nothing sent
    np.testing.assert_array_equal(robot.joint_positions().q, q1)
    robot.jog("cartesian", 2, 0.01)  # default: the 0.25 m/s cap itself
    q2 = robot.joint_positions().q
    d = world.nominal.position(q2) - p0
    # bound from tick quantisation: half a tick per joint through the position Jacobian
    J = world.nominal.jacobian_q(q2)[0, :3]
    bound = float(np.sum(np.linalg.norm(J, axis=0) * np.array([_tick(world, j) for j in range(4)]) / 2))
    assert abs(d[2] - 0.01) <= bound and np.hypot(d[0], d[1]) <= bound
    # the profile velocities written keep the tool at or below 0.25 m/s
    vel = np.array([emu.devices[i].get("profile_velocity") for i in IDS]) * 0.229 * 2 * np.pi / 60
    dq = q2 - q1
    tool_speed = np.linalg.norm(J @ (np.sign(dq) * vel))
    assert tool_speed <= 0.25 * 1.05


def test_writeback_round_trips_and_survives_a_power_cycle(robot_rig):
    world = World.default(model="omx", seed=2, start=[0.1, 0.2, 0.3, 0.4])
    emu, robot = robot_rig("dynamixel", world, ids=IDS, query="&latency=50")
    assert robot.read_calibration() == {f"offset.j{k}": 0.0 for k in range(1, 5)}
    want = {"offset.j1": 0.0123, "offset.j2": -0.0456, "offset.j4": 0.2}
    to_write_pose(robot, want)
    q_before = robot.joint_positions().q
    robot.write_calibration(want)
    got = robot.read_calibration()
    for k in range(4):
        tick = _tick(world, k)
        assert abs(got[f"offset.j{k + 1}"] - want.get(f"offset.j{k + 1}", 0.0)) <= tick / 2 + 1e-12
    assert robot.status().enabled  # torque state restored after the EEPROM write
    shift = robot.joint_positions().q - q_before  # the same physical pose: the readings moved by the offsets
    assert np.allclose(shift, [got[f"offset.j{k}"] for k in range(1, 5)], atol=1e-12)
    with pytest.raises(ConfigError):
        robot.write_calibration({"dh.j1.a": 0.1})
    with pytest.raises(LimitError):
        robot.write_calibration({"offset.j1": 1e4})
    robot.close()
    eeprom = emu.eeprom()
    emu.stop()
    # power cycle: a new emulator keeps the EEPROM images, RAM restarts (torque off; the arm stands where the
    # write left it: no written joint carries gravity torque there)
    emu, robot = robot_rig("dynamixel", world, ids=IDS, eeprom=eeprom, query="&latency=50", enable=False)
    assert robot.read_calibration() == got
    assert not robot.status().enabled
    q = robot.joint_positions().q
    assert np.all(np.abs(q - (world.encoder_q() + [got[f"offset.j{k}"] for k in range(1, 5)]))
                  <= _tick(world, 0) / 2 + 1e-12)


def test_compliant_mode_seats_in_socket_and_touch_reads_contact(rig):
    world, emu, robot = rig
    robot.enable()
    sock = world.points["A"]
    assert robot.touch() is False
    # bring the TRUE tip within the capture radius (the test knows the truth; the station would not)
    res = world.truth.ik(sock.position + np.array([0.002, 0.0, 0.002]), np.array([0.0, 0.5, 0.3, 0.8]))
    assert res.ok[0]
    robot.move_joints(res.q[0])
    assert robot.touch() is False
    n0 = robot.bus.transactions
    robot.set_compliant(True)
    # Goal PWM and torque on (sync writes; the torque never goes off: no brake), one read-back of 64..135
    assert robot.bus.transactions - n0 == 3
    assert robot.status().compliant
    assert [emu.devices[i].get("goal_pwm") for i in IDS] == [90] * 4
    assert [emu.devices[i].get("operating_mode") for i in IDS] == [3] * 4  # no mode switch (EEPROM, torque off)
    assert world.seated == "A"
    assert robot.touch() is True
    seated = world.encoder_q()
    robot.set_compliant(False)
    assert [emu.devices[i].get("goal_pwm") for i in IDS] == [885] * 4  # back to the PWM Limit (36)
    # the arm holds where the socket put it, and the readout follows the truth there
    snap = robot.joint_positions()
    assert np.all(np.abs(snap.q - seated) <= _tick(world, 0) / 2 + 1e-12)
    assert np.linalg.norm(world.tip_true() - sock.position) < 1e-4


def test_needle_contact_through_the_contact_sensor(robot_rig):
    cell = {"contact_radius": 0.002,
            "points": [{"label": "N", "kind": "needle", "position": [0.18, 0.08, 0.05], "approach": [0, 0, 1]}]}
    world = World.default(model="omx", seed=1, cell=cell)
    emu, robot = robot_rig("dynamixel", world, ids=IDS, contact_id=210, query="&latency=50")
    assert "contact=210" in emu.url
    needle = world.points["N"].position
    res = world.truth.ik(needle, np.array([0.4, 0.5, 0.3, 0.8]))
    robot.move_joints(res.q[0])
    assert robot.touch() is True
    robot.jog("cartesian", 2, 0.01)
    assert robot.touch() is False
    assert emu.devices[210].get("contact_count") == 1


def test_url_errors_are_config_errors():
    with pytest.raises(ConfigError, match="unknown option"):
        open_robot("dynamixel:///dev/null?ids=1-4&bogus=1")
    with pytest.raises(ConfigError, match="ids"):
        open_robot("dynamixel:///dev/null?ids=1-3&model=omx")


def test_goal_refused_by_servo_position_limits_is_caught_at_once(rig):
    world, emu, robot = rig
    robot.enable()
    # a technician narrowed servo 12's Max Position Limit (EEPROM 48) to 2100 ticks (~ +0.08 rad)
    robot.disable()
    assert robot.bus.write(12, 48, 4, 2100) == 0
    robot.enable()
    before = world.encoder_q()
    with pytest.raises(DeviceFault, match=r"servo id 12 \(joint 2 shoulder\) refused the goal"):
        robot.move_joints(np.array([before[0], 0.5, before[2], before[3]]), wait=False)
    # nothing moved: the torque was off for the EEPROM write and a DYNAMIXEL has no brake, so the arm fell where
    # gravity took it and the servos hold it there, at their resolution (goal := present, in whole ticks)
    assert np.all(np.abs(world.encoder_q() - before) <= [_tick(world, j) for j in range(4)])


def test_xl430_arm_reads_moves_and_is_compliant_through_goal_pwm():
    # its own rig: the URL names no ids (the driver's default, 1-4), which robot_rig's emulator URL always spells
    # out
    world = World.default(model="omx", seed=8)
    with DynamixelEmulator(world, ids=[1, 2, 3, 4], servo="xl430", contact_id=None) as emu, \
            open_robot(f"dynamixel://{emu.path}?model=omx&servo=xl430-w250&latency=50") as robot:
        assert [d["model"] for d in robot.identity().devices] == ["XL430-W250"] * 4
        assert robot.touch() is None
        robot.enable()
        target = np.array([-0.3, 0.4, 0.2, -0.5])
        robot.move_joints(target)
        assert np.all(np.abs(robot.joint_positions().q - target) <= _tick(world, 0) / 2 + 1e-12)
        robot.set_compliant(True)  # Goal PWM limits every position mode: no current sensing needed
        assert robot.status().compliant and world.compliant
        robot.set_compliant(False)
        assert not world.compliant and robot.status().enabled
