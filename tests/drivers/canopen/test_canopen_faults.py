"""Each bus fault produces its typed error and leaves the robot stopped (real World in realtime, real
canopen + python-can on a virtual bus)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from station.mocks.world import World

from station.robot import BusError, ConnectionLost, DeviceFault

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]
TARGET = np.array(START) + np.array([0.4, 0.3, -0.4, 0.5, 0.4, 0.6])


@pytest.fixture
def moving(robot_rig):
    """A robot in the middle of a slow realtime move."""
    world = World.default(model="arm6", seed=11, start=START, time_mode="realtime")
    emu, robot = robot_rig("canopen", world, query="&heartbeat_ms=100")
    robot.move_joints(TARGET, speed=0.3, wait=False)
    time.sleep(0.1)
    assert world.is_moving()
    return world, emu, robot


def wait_fault(robot, timeout: float = 2.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            robot.joint_positions()
        except Exception as e:  # noqa: BLE001 - the test inspects the type
            return e
        time.sleep(0.01)
    raise AssertionError("no fault raised")


def assert_stopped(world, robot):
    end = time.monotonic() + 1.5
    while world.is_moving() and time.monotonic() < end:
        time.sleep(0.02)
    assert not world.is_moving()
    assert not robot.status().enabled
    assert np.max(np.abs(world.encoder_q() - TARGET)) > 0.05  # it did not finish the move


def test_emcy_is_device_fault_naming_node_and_code_then_recovers(moving):
    world, emu, robot = moving
    world.faults.inject("device_fault", device=3, code=0x4310)
    err = wait_fault(robot)
    assert isinstance(err, DeviceFault)
    assert "node 3" in str(err) and "0x4310" in str(err) and err.code == 0x4310
    assert_stopped(world, robot)
    st = robot.status()
    assert any("node 3" in f for f in st.faults) and st.joints[2].fault == "EMCY 0x4310"
    with pytest.raises(DeviceFault):
        robot.move_joints(TARGET)  # latched until enable()
    robot.enable()
    assert robot.status().enabled and not robot.status().faults
    robot.move_joints(TARGET, speed=1.0)
    assert np.max(np.abs(world.encoder_q() - TARGET)) < 1e-5


def test_heartbeat_loss_is_connection_lost_and_clears_when_node_returns(moving):
    world, emu, robot = moving
    t0 = time.monotonic()
    world.faults.inject("timeout", device=5)
    err = wait_fault(robot)
    assert isinstance(err, ConnectionLost) and "node 5" in str(err) and "heartbeat" in str(err)
    assert time.monotonic() - t0 < 1.0  # 3 heartbeat periods + 0.2 s margin, not a long hang
    assert_stopped(world, robot)
    with pytest.raises(ConnectionLost):
        robot.enable()  # node still silent
    time.sleep(1.0)  # the emulated timeout ends; heartbeats come back
    robot.enable()
    assert robot.status().enabled


def test_disconnect_stays_connection_lost(moving):
    world, emu, robot = moving
    world.faults.inject("disconnect", device=2)
    err = wait_fault(robot)
    assert isinstance(err, ConnectionLost) and "node 2" in str(err)
    assert_stopped(world, robot)
    time.sleep(0.3)
    with pytest.raises(ConnectionLost):
        robot.enable()


def test_corrupted_frames_are_bus_error(moving):
    """Two frames destroyed within a second (more than the ``error_frames=1`` tolerated): BusError, stopped."""
    world, emu, robot = moving
    world.faults.inject("corrupt", device=4, count=2)
    err = wait_fault(robot)
    assert isinstance(err, BusError) and not isinstance(err, ConnectionLost)
    assert "error frames" in str(err) and "2 within 1 s" in str(err) and "\n" not in str(err)
    assert_stopped(world, robot)


def test_an_isolated_error_frame_is_tolerated_as_documented(moving):
    """docs/hardware-canopen.md: one error frame (a frame the sender retransmits) is not a fault; the move goes
    on to its target. One more within the same second is; error frames further apart never add up."""
    world, emu, robot = moving
    emu.inject_error_frame("protocol")
    time.sleep(0.3)
    robot.joint_positions()  # no fault latched
    assert robot.faults.error is None and world.is_moving()
    time.sleep(0.8)  # > 1 s after the first
    emu.inject_error_frame("protocol")
    time.sleep(0.2)
    assert robot.faults.error is None
    emu.inject_error_frame("protocol")  # the second within 1 s
    err = wait_fault(robot)
    assert isinstance(err, BusError) and "2 within 1 s" in str(err), err
    end = time.monotonic() + 1.5
    while world.is_moving() and time.monotonic() < end:
        time.sleep(0.02)
    assert not world.is_moving()


def test_error_frames_option_raises_the_tolerance(robot_rig):
    world = World.default(model="arm6", seed=11, start=START, time_mode="realtime")
    emu, robot = robot_rig("canopen", world, query="&error_frames=3")
    for _ in range(3):
        emu.inject_error_frame("protocol")
    time.sleep(0.2)
    robot.joint_positions()
    assert robot.faults.error is None
    emu.inject_error_frame("protocol")
    err = wait_fault(robot)
    assert isinstance(err, BusError) and "4 within 1 s" in str(err) and "3 tolerated" in str(err), err


def test_bus_off_is_bus_error(moving):
    world, emu, robot = moving
    emu.inject_error_frame("busoff")
    err = wait_fault(robot)
    assert isinstance(err, BusError) and "bus-off" in str(err)
    assert_stopped(world, robot)
    robot.stop()  # never raises, even latched
    assert "bus-off" in " ".join(robot.status().faults)


def test_node_reboot_is_connection_lost(moving):
    world, emu, robot = moving
    emu.power_cycle([6])
    err = wait_fault(robot)
    assert isinstance(err, ConnectionLost) and "node 6 rebooted" in str(err)
    assert_stopped(world, robot)
    time.sleep(0.2)  # heartbeats of the rebooted drive are back, but its configuration is gone
    with pytest.raises(ConnectionLost, match="rebooted"):
        robot.enable()
