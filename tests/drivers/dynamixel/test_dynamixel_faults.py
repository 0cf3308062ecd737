"""Bus and device faults: each gives its typed error and leaves the arm stopped (real SDK over a pty)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.world import World

from station.robot import BusError, ConnectionLost, DeviceFault, open_robot

IDS = [11, 12, 13, 14]
TARGET = np.array([1.0, 0.5, -0.5, 0.8])


@pytest.fixture()
def sim():
    """Simulated time: the test decides when time passes, so a fault lands mid-move deterministically."""
    world = World.default(model="omx", seed=4, time_mode="sim")
    emu = DynamixelEmulator(world, ids=IDS)
    robot = open_robot(f"dynamixel://{emu.start().path}?ids=11-14&model=omx&retries=3&latency=50")
    robot.enable()
    yield world, emu, robot
    robot.close()
    emu.stop()


def _start_move(world, robot):
    robot.move_joints(TARGET, speed=1.0, wait=False)
    robot.joint_positions()  # a round trip: the emulator has applied the (unanswered) sync write
    world.advance(0.3)
    assert world.is_moving()
    return world.encoder_q()


def _assert_stopped_near(world, q_fault, free: tuple[int, ...] = ()):
    """Holding: the world settles near where the fault struck (braking distance), far from the target. The joints
    in ``free`` lost their torque (a servo's shutdown on a hardware error): a DYNAMIXEL has no brake (e-Manual,
    Torque Enable: free run), so those fall where gravity takes them; the others hold."""
    world.run_until_idle()
    q = world.encoder_q()
    assert not world.is_moving()
    held = [j for j in range(len(q)) if j not in free]
    assert np.max(np.abs(q - q_fault)[held]) < 0.15
    assert not any(world.enabled()[j] for j in free)
    assert np.max(np.abs(q - TARGET)[held]) > 0.3


def test_transient_timeouts_and_corruption_are_retried(sim):
    world, emu, robot = sim
    emu.reset_stats()
    world.faults.inject("timeout", count=2)
    q = robot.joint_positions().q
    assert emu.stats["by_inst"] == {"fast_sync_read": 3}  # two lost answers, then success
    world.faults.inject("corrupt", count=1)
    q2 = robot.joint_positions().q
    assert emu.stats["by_inst"] == {"fast_sync_read": 5}
    assert np.array_equal(q, q2)
    assert robot.bus.retried == 3


@pytest.mark.parametrize("kind, error", [("timeout", ConnectionLost), ("corrupt", BusError)])
def test_persistent_bus_fault_raises_its_error_and_stops(sim, kind, error):
    """4 lost / damaged answers in a row (1 try + 3 retries): no answer is ConnectionLost, damaged answers a
    BusError that is not a lost connection; the arm stops either way."""
    world, emu, robot = sim
    q_fault = _start_move(world, robot)
    world.faults.inject(kind, count=4)
    with pytest.raises(BusError) as e:
        robot.joint_positions()
    assert isinstance(e.value, error) and (kind == "timeout") == isinstance(e.value, ConnectionLost)
    if kind == "timeout":
        assert "after 4 attempt" in str(e.value)
    _assert_stopped_near(world, q_fault)


def test_device_fault_names_servo_and_bits_and_reboot_recovers(sim):
    world, emu, robot = sim
    q_fault = _start_move(world, robot)
    world.faults.inject("device_fault", device=13)
    with pytest.raises(DeviceFault) as e:
        robot.joint_positions()
    msg = str(e.value)
    assert "servo id 13" in msg and "elbow" in msg and "0x20" in msg and "overload" in msg
    assert "power-cycle the servos (elbow included)" in msg and "robot." not in msg  # nothing a CLI user can't do
    assert e.value.device == "dynamixel:13" and e.value.code == 0x20
    _assert_stopped_near(world, q_fault, free=(2,))  # the elbow's servo shut down: it falls
    st = robot.status()
    assert not st.ok and not st.enabled and st.joints[2].fault and st.joints[0].enabled
    with pytest.raises(DeviceFault):
        robot.enable()  # refused while the error is latched
    robot.reboot("elbow")
    robot.enable()
    assert robot.status().ok
    robot.move_joints(TARGET, speed=1.0, wait=False)
    robot.joint_positions()
    world.run_until_idle()
    assert np.max(np.abs(robot.joint_positions().q - TARGET)) < 2e-3


def test_device_fault_during_a_waited_move():
    world = World.default(model="omx", seed=4, time_mode="realtime")
    with DynamixelEmulator(world, ids=IDS) as emu, \
            open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&latency=50") as robot:
        robot.enable()
        world.faults.inject("device_fault", device=12, after=8)  # strikes while polling
        with pytest.raises(DeviceFault, match="servo id 12"):
            robot.move_joints(TARGET, speed=1.0)
        q_fault = world.encoder_q()
        deadline = time.monotonic() + 1.0  # braking from <= 1 rad/s takes a fraction of that
        while world.is_moving() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not world.is_moving()
        held = [0, 2, 3]  # the shoulder's servo shut down: no brake, it falls (e-Manual, Torque Enable); the rest hold
        assert not world.enabled()[1]
        assert np.max(np.abs(world.encoder_q() - q_fault)[held]) < 0.1
        assert np.max(np.abs(world.encoder_q() - TARGET)[held]) > 0.3


def test_disconnect_mid_move_bus_watchdog_stops_the_arm():
    world = World.default(model="omx", seed=4, time_mode="realtime")
    with DynamixelEmulator(world, ids=IDS) as emu, \
            open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&latency=50") as robot:
        robot.enable()
        world.faults.inject("disconnect", after=8)
        t0 = time.monotonic()
        with pytest.raises(ConnectionLost):
            robot.move_joints(TARGET, speed=1.0)
        assert time.monotonic() - t0 < 1.5  # bounded retries, not the move's duration
        time.sleep(0.4)  # 0.2 s watchdog + braking
        assert not world.is_moving()
        assert np.max(np.abs(world.encoder_q() - TARGET)) > 0.3
        assert all(emu.devices[i].get("bus_watchdog") == 255 for i in IDS)


def _trip_watchdogs(emu, robot):
    """Arm every servo's bus watchdog (20 ms) and keep the bus quiet: they trip (98 reads 255)."""
    robot.bus.sync_write(98, 1, {i: 1 for i in IDS})
    end = time.monotonic() + 2.0
    while not all(emu.devices[i].get("bus_watchdog") == 255 for i in IDS) and time.monotonic() < end:
        time.sleep(0.05)
    assert all(emu.devices[i].get("bus_watchdog") == 255 for i in IDS)


def test_enable_clears_a_tripped_bus_watchdog():
    """After a run died mid-move the watchdogs are tripped and refuse goals; enable() clears them (no move
    needed), confirmed by its read-back."""
    world = World.default(model="omx", seed=4, time_mode="realtime")
    with DynamixelEmulator(world, ids=IDS) as emu, \
            open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&latency=50") as robot:
        robot.enable()
        _trip_watchdogs(emu, robot)
        st = robot.status()
        assert len(st.faults) == 4 and all("bus watchdog tripped" in f for f in st.faults)
        robot.enable()
        assert not robot.status().faults
        assert all(emu.devices[i].get("bus_watchdog") == 0 for i in IDS)
        robot.move_joints(TARGET, speed=2.0)
        assert np.max(np.abs(robot.joint_positions().q - TARGET)) < 2e-3
        assert all(emu.devices[i].get("bus_watchdog") == 0 for i in IDS)  # disarmed after the move



def _late_station(robot, stalls: set[int], seconds: float = 0.35):
    """The station's own lateness: before the sync reads numbered in ``stalls`` (1 = the first of the move), the
    driver's thread sleeps ``seconds``, longer than the servos' 0.2 s bus watchdog (a loaded host does this)."""
    read = robot.bus.sync_read
    calls = [0]

    def late(*a, **k):
        calls[0] += 1
        if calls[0] in stalls:
            time.sleep(seconds)
        return read(*a, **k)
    robot.bus.sync_read = late
    return calls


def test_a_station_late_on_the_bus_finds_the_arm_stopped_and_sends_the_move_again(caplog):
    """The servos' bus watchdog stops the arm when the station is quiet for 0.2 s, as on the device; a driver
    that was itself quiet that long says so and sends the same move again from where the arm stopped."""
    world = World.default(model="omx", seed=4, time_mode="realtime")
    with DynamixelEmulator(world, ids=IDS) as emu, \
            open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&latency=50") as robot:
        robot.enable()
        late = _late_station(robot, {4})
        with caplog.at_level("WARNING", logger="station.drivers.dynamixel"):
            robot.move_joints(TARGET, speed=1.0)
        assert late[0] > 4
        said = [r.getMessage() for r in caplog.records if "quiet on the bus" in r.getMessage()]
        assert len(said) == 1 and "sent again" in said[0], said
        assert np.max(np.abs(world.encoder_q() - TARGET)) < 2e-3
        robot.joint_positions()  # a round trip: the emulator has applied the (unanswered) sync write
        assert all(emu.devices[i].get("bus_watchdog") == 0 for i in IDS)  # disarmed after the move


def test_a_station_late_every_time_stops_in_one_line():
    world = World.default(model="omx", seed=4, time_mode="realtime")
    with DynamixelEmulator(world, ids=IDS) as emu, \
            open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&latency=50") as robot:
        robot.enable()
        _late_station(robot, set(range(2, 200)))
        with pytest.raises(DeviceFault) as e:
            robot.move_joints(TARGET, speed=1.0)
        assert "4 time(s) in a row (the host is overloaded)" in str(e.value)
        time.sleep(0.1)
        assert not world.is_moving()
        assert np.max(np.abs(world.encoder_q() - TARGET)) > 0.1  # four short stretches, each stopped
        robot.bus.sync_read = type(robot.bus).sync_read.__get__(robot.bus)
        robot.move_joints(TARGET, speed=2.0)  # the next move clears the tripped watchdogs first
        assert np.max(np.abs(world.encoder_q() - TARGET)) < 2e-3


def test_a_watchdog_trip_while_the_station_talked_is_lost_packets_not_resent():
    """Servo 12 stops hearing the bus for longer than its watchdog while the station keeps polling: that is
    not the station's lateness; the move is not sent again, the error names the bus."""
    world = World.default(model="omx", seed=4, time_mode="realtime")
    with DynamixelEmulator(world, ids=IDS) as emu, \
            open_robot(f"dynamixel://{emu.path}?ids=11-14&model=omx&latency=50") as robot:
        robot.enable()
        read = robot.bus.sync_read
        calls = [0]

        def deaf_12(*a, **k):
            calls[0] += 1
            if calls[0] == 3:  # what servo 12 last heard is 1 s old: its own watchdog trips at the next check
                with emu._lock:
                    emu._last_rx[12] -= 1.0
                time.sleep(0.05)
            return read(*a, **k)
        robot.bus.sync_read = deaf_12
        with pytest.raises(DeviceFault) as e:
            robot.move_joints(TARGET, speed=1.0)
        msg = str(e.value)
        assert "bus watchdog of servo id 12" in msg and "packets are being lost" in msg, msg
        time.sleep(0.4)
        assert not world.is_moving()
        assert np.max(np.abs(world.encoder_q() - TARGET)) > 0.3
