"""DYNAMIXEL as the ROBOTIS e-Manual documents it (docs/hardware-dynamixel.md, conformance table): the emulator
behaves so on the wire (the real dynamixel_sdk over a pty) and the driver honours it, each checked against the
simulated world's truth. Every test here failed on the emulator and driver before they followed the e-Manual."""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import dynamixel_sdk as sdk
import numpy as np
import pytest
from station.drivers.dynamixel.bus import DxlPort
from station.mocks.world import World

from station.robot import DeviceFault, LimitError, open_robot

IDS = [11, 12, 13, 14]
START = [0.2, -0.3, 0.4, 0.1]  # the shoulder and elbow carry gravity torque here
DRIVE_MODE, OPERATING_MODE, HOMING_OFFSET, TORQUE, SRL = 10, 11, 20, 64, 68
PROFILE_ACCELERATION, PROFILE_VELOCITY, GOAL, PRESENT = 108, 112, 116, 132


def _tick(world, j):
    e = world.nominal.joints[j].encoder
    return 1.0 / (e.counts_per_unit * e.gear)


def _counts(world, j):
    return int(round(float(world.nominal.joints[j].encoder.to_counts(world.encoder_q()[j]))))


def _signed(v: int) -> int:
    return v - (1 << 32) if v >= 1 << 31 else v


class Wire:
    """The SDK on the emulator's pty, for what a technician sets with DYNAMIXEL Wizard before the station."""

    def __init__(self, emu) -> None:
        self.port = DxlPort(emu.path, latency_ms=50)
        assert self.port.openPort() and self.port.setBaudRate(1_000_000)
        self.ph = sdk.PacketHandler(2.0)

    def write(self, i, addr, size, value):
        fn = {1: self.ph.write1ByteTxRx, 4: self.ph.write4ByteTxRx}[size]
        return fn(self.port, i, addr, int(value) & ((1 << (8 * size)) - 1))

    def read(self, i, addr, size=4):
        fn = {1: self.ph.read1ByteTxRx, 2: self.ph.read2ByteTxRx, 4: self.ph.read4ByteTxRx}[size]
        value, res, _ = fn(self.port, i, addr)
        assert res == sdk.COMM_SUCCESS
        return _signed(value) if size == 4 else value

    def close(self):
        self.port.closePort()


def _after(world, done, timeout: float = 20.0) -> np.ndarray:
    """The world's joint positions once ``done(q)`` holds (a fall the emulator hands to the world takes its time)."""
    end = time.monotonic() + timeout
    while not done(q := world.encoder_q()) and time.monotonic() < end:
        time.sleep(0.01)
    return q


def _write_pose(robot, values=None):
    """What the station's write-back does first (station.engine.writeback.to_write_pose, without a cell)."""
    for _ in range(40):
        q = robot.write_pose(values)
        if q is None:
            return
        robot.move_joints(q)
    raise AssertionError("no write pose within 40 moves")


class Releases:
    """Every torque-off the world sees: the joint, gravity's torque on it, its friction and where the arm was."""

    def __init__(self, world, monkeypatch) -> None:
        self.seen: list[tuple[int, float, float]] = []
        orig = type(world).set_enabled

        def set_enabled(w, on, joints=None):
            if not on:
                idx = range(w.n_joints) if joints is None else np.atleast_1d(joints)
                tau, fr = w.gravity_torque(), w.dynamics_friction()
                self.seen += [(int(j), float(tau[j]), float(fr[j])) for j in idx if w.enabled()[j]]
            return orig(w, on, joints)
        monkeypatch.setattr(type(world), "set_enabled", set_enabled)


@pytest.fixture
def rig(robot_rig):
    """The servos alone (no driver yet): a test sets them up as a technician would before the station opens them."""
    world = World.default(model="omx", seed=7, start=START)
    emu, _ = robot_rig("dynamixel", world, ids=IDS, connect=False)
    return world, emu


# ---- Torque Enable: free run, no brake ---------------------------------------------------------------------
def test_torque_off_is_free_run_the_arm_falls(rig):
    """e-Manual, Torque Enable: 0 = "Torque OFF (Free-run)". Powered on, the arm rests where it stands; once the
    servos held it and let go, every joint gravity loads falls (no brake), and Present Position follows it."""
    world, emu = rig
    assert not world.brakes.any()
    q0 = world.encoder_q().copy()
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        held = world.encoder_q().copy()  # where it stood, to the servos' tick (goal := present)
        np.testing.assert_allclose(held, q0, atol=_tick(world, 0))
        robot.bus.write(11, TORQUE, 1, 0)  # the waist: a vertical axis, gravity never turns it
        robot.bus.write(12, TORQUE, 1, 0)  # the shoulder
        fell = _after(world, lambda q: abs(q[1] - held[1]) > 0.3)  # a fall takes its time (the world's, here)
        assert emu.settled()  # (until then the servos answer with where the fall began)
        assert abs(fell[1] - held[1]) > 0.3 and fell[0] == held[0]  # the shoulder falls, the waist stays
        np.testing.assert_allclose(fell[2:], held[2:])  # the others hold
        np.testing.assert_allclose(robot.joint_positions().q, fell, atol=_tick(world, 1))


def test_compliance_never_turns_the_torque_off(rig, monkeypatch):
    """Operating Mode is EEPROM (written only with the torque off): compliance switches Goal PWM (RAM) instead, so
    the arm never goes limp where gravity loads it; the mode stays position control."""
    world, emu = rig
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        q0 = world.encoder_q().copy()
        rel = Releases(world, monkeypatch)
        robot.set_compliant(True)
        assert world.compliant and robot.status().compliant
        robot.set_compliant(False)
        assert rel.seen == [] and world.enabled().all()
        assert [emu.devices[i].get("operating_mode") for i in IDS] == [3] * 4
        np.testing.assert_allclose(world.encoder_q(), q0, atol=max(_tick(world, j) for j in range(4)))


# ---- the write-back on an arm without brakes ----------------------------------------------------------------
def test_write_calibration_is_refused_where_gravity_loads_a_joint(rig, monkeypatch):
    """Homing Offset is EEPROM: the servo takes it only with its torque off. Where a joint to be written carries
    gravity torque the driver refuses in one line and writes nothing (the joint would fall)."""
    world, emu = rig
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        q0 = world.encoder_q().copy()
        rel = Releases(world, monkeypatch)
        with pytest.raises(DeviceFault) as e:
            robot.write_calibration({"offset.j2": 0.01, "offset.j3": -0.01})
        assert "\n" not in str(e.value) and "shoulder" in str(e.value) and "write_pose" in str(e.value)
        assert [emu.devices[i].get("homing_offset") for i in IDS] == [0] * 4
        assert rel.seen == [] and np.array_equal(world.encoder_q(), q0)


def test_write_calibration_one_servo_at_a_time_where_nothing_falls(rig, monkeypatch):
    """At the pose write_pose() finds (by the servos' own Present Current), each servo is released alone while
    the others hold, gravity's torque on it below what its gears hold: no joint moves a tick, and every reading
    changes by exactly its offset (the proof that the servo applies it)."""
    world, emu = rig
    values = {"offset.j1": 0.02, "offset.j2": -0.01, "offset.j3": 0.015, "offset.j4": 0.01}
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        _write_pose(robot, values)
        q0, read0 = world.encoder_q().copy(), robot.joint_positions().q
        rel = Releases(world, monkeypatch)
        robot.write_calibration(values)
        assert emu.settled()
        assert sorted(j for j, _, _ in rel.seen) == [0, 1, 2, 3]  # one release per servo
        assert all(abs(tau) < fr for _, tau, fr in rel.seen), rel.seen
        assert np.max(np.abs(world.encoder_q() - q0)) == 0 and world.enabled().all()
        got = robot.read_calibration()
        shift = robot.joint_positions().q - read0
        np.testing.assert_allclose(shift, [got[f"offset.j{k}"] for k in range(1, 5)], atol=1e-12)
        for k in range(4):
            assert abs(got[f"offset.j{k + 1}"] - values[f"offset.j{k + 1}"]) <= _tick(world, k) / 2 + 1e-12


# ---- Homing Offset: range per operating mode ------------------------------------------------------------------
def test_homing_offset_beyond_1024_is_ignored_in_position_mode(rig):
    """e-Manual, Homing Offset: in Position Control Mode an offset outside -1,024..1,024 is ignored (stored, read
    back, not applied); Extended Position Control Mode applies it. The driver refuses such an offset in mode 3."""
    world, emu = rig
    wire = Wire(emu)
    try:
        before = wire.read(11, PRESENT)
        assert wire.write(11, HOMING_OFFSET, 4, 2000) == (sdk.COMM_SUCCESS, 0)
        assert wire.read(11, HOMING_OFFSET) == 2000 and wire.read(11, PRESENT) == before  # ignored
        assert wire.write(11, HOMING_OFFSET, 4, 1000) == (sdk.COMM_SUCCESS, 0)
        assert wire.read(11, PRESENT) == before + 1000
        assert wire.write(11, OPERATING_MODE, 1, 4) == (sdk.COMM_SUCCESS, 0)
        assert wire.write(11, HOMING_OFFSET, 4, 2000) == (sdk.COMM_SUCCESS, 0)
        assert wire.read(11, PRESENT) == before + 2000  # extended position: applied
        assert wire.write(11, HOMING_OFFSET, 4, 0) == (sdk.COMM_SUCCESS, 0)
        assert wire.write(11, OPERATING_MODE, 1, 3) == (sdk.COMM_SUCCESS, 0)
    finally:
        wire.close()
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        with pytest.raises(LimitError, match=r"1024 ticks servo 12 applies in operating mode 3"):
            robot.write_calibration({"offset.j2": 1.6})  # 1043 ticks
    assert emu.devices[12].get("homing_offset") == 0


# ---- Drive Mode: reverse direction, time-based profile ---------------------------------------------------------
def test_reverse_mode_turns_positions_around_and_the_driver_honours_it(rig):
    """e-Manual, Drive Mode bit 0: Goal and Present Position turn around (the homing offset keeps its sign).
    After the servo restarts its reading lies within one turn. The driver reads the bit: same joint angles, same
    moves, offsets written with the servo's sign."""
    world, emu = rig
    wire = Wire(emu)
    try:
        c = _counts(world, 1)
        assert wire.write(12, DRIVE_MODE, 1, 1) == (sdk.COMM_SUCCESS, 0)
        assert wire.ph.reboot(wire.port, 12)[0] == sdk.COMM_SUCCESS
        assert wire.read(12, PRESENT) == (-c) % 4096
    finally:
        wire.close()
    with open_robot(f"{emu.url}&latency=50") as robot:
        assert robot.identity().devices[1]["drive_mode"] == 1
        np.testing.assert_allclose(robot.joint_positions().q, world.encoder_q(), atol=_tick(world, 1) / 2 + 1e-12)
        robot.enable()
        target = np.array([0.1, 0.35, -0.2, 0.3])
        robot.move_joints(target, speed=1.0)
        np.testing.assert_allclose(world.encoder_q(), target, atol=_tick(world, 1) / 2 + 1e-12)
        _write_pose(robot, {"offset.j2": 0.01})
        robot.write_calibration({"offset.j2": 0.01})
        assert emu.devices[12].get("homing_offset") == -round(0.01 * 4096 / (2 * math.pi))
        np.testing.assert_allclose(robot.joint_positions().q[1], world.encoder_q()[1] + robot.read_calibration()[
            "offset.j2"], atol=1e-12)


def test_time_based_profile_sets_the_move_time(robot_rig):
    """e-Manual, Drive Mode bit 2 and Profile Velocity: with the time-based profile Profile Velocity is the time
    span of the move and Profile Acceleration its accelerating time, in ms. The driver writes ms to such a servo:
    the move takes the time it planned, not the ~0.1 s a velocity read as ms-as-units would give."""
    world = World.default(model="omx", seed=7, start=START, time_mode="sim")
    emu, _ = robot_rig("dynamixel", world, ids=IDS, connect=False)
    wire = Wire(emu)
    try:
        for i in IDS:
            assert wire.write(i, DRIVE_MODE, 1, 4) == (sdk.COMM_SUCCESS, 0)
        assert wire.write(13, TORQUE, 1, 1) == (sdk.COMM_SUCCESS, 0)
        assert wire.write(13, PROFILE_VELOCITY, 4, 1500) == (sdk.COMM_SUCCESS, 0)  # 1.5 s
        assert wire.write(13, PROFILE_ACCELERATION, 4, 300) == (sdk.COMM_SUCCESS, 0)  # 0.3 s accelerating
        assert wire.write(13, GOAL, 4, wire.read(13, PRESENT) + 300) == (sdk.COMM_SUCCESS, 0)
        assert world.is_moving()
        assert abs(world.run_until_idle() - 1.5) < 0.01
        assert wire.write(13, TORQUE, 1, 0) == (sdk.COMM_SUCCESS, 0)
    finally:
        wire.close()
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        target = np.array(START) + [0.4, 0.2, -0.3, 0.1]
        robot.move_joints(target, speed=0.5, wait=False)
        pv = [emu.devices[i].get("profile_velocity") for i in IDS]
        pa = [emu.devices[i].get("profile_acceleration") for i in IDS]
        assert len(set(pv)) == 1 and len(set(pa)) == 1 and 2 * pa[0] <= pv[0]  # one time span for all joints
        assert pv[0] / 1000 >= 0.4 / 0.5  # the lead joint at no more than 0.5 rad/s
        assert abs(world.run_until_idle() - pv[0] / 1000) < 0.01
        np.testing.assert_allclose(world.encoder_q(), target, atol=_tick(world, 0) / 2 + 1e-12)


# ---- Present Position: one turn after power-on, reboot, mode switch ------------------------------------------
def _omx_zero_at_0(tmp_path: Path) -> str:
    """The omx with its waist's encoder zero at 0 ticks: the joint's range crosses the servo's 0/4095."""
    src = Path(__file__).parents[3] / "station" / "kinematics" / "models" / "omx.yaml"
    text = src.read_text().replace("name: omx", "name: omx-zero0", 1)
    line = next(ln for ln in text.splitlines() if "name: waist" in ln)
    path = tmp_path / "omx-zero0.yaml"
    path.write_text(text.replace(line, line.replace("zero: 2048", "zero: 0")))
    return str(path)


def test_present_position_resets_to_one_turn_and_the_driver_is_not_fooled(robot_rig, tmp_path):
    """e-Manual, operating mode note: Present Position is reset to an absolute value within one full rotation at
    power-on and at a reboot (and on a switch to / torque on in Position Control Mode). A waist whose zero is the
    servo's 0 reads -326 ticks at -0.5 rad as 3770 after power-on; in Extended Position Control Mode it counts on
    past 4096 and reads one turn less after a reboot. The driver unwraps every reading into the joint's range."""
    model = _omx_zero_at_0(tmp_path)
    world = World.default(model=model, seed=7, start=[-0.5, -0.3, 0.4, 0.1])
    emu, _ = robot_rig("dynamixel", world, ids=IDS, connect=False)
    wire = Wire(emu)
    try:
        assert wire.read(11, PRESENT) == -326 % 4096  # power-on: within one turn
        assert wire.write(11, OPERATING_MODE, 1, 4) == (sdk.COMM_SUCCESS, 0)
    finally:
        wire.close()
    with open_robot(f"{emu.url}&model={model}&latency=50") as robot:
        np.testing.assert_allclose(robot.joint_positions().q, world.encoder_q(), atol=_tick(world, 0) / 2 + 1e-12)
        robot.enable()
        robot.move_joints(np.array([0.5, -0.3, 0.4, 0.1]))
        assert emu.devices[11].get("present_position") == 326 + 4096  # extended: counting on
        robot.reboot("waist")
        assert emu.devices[11].get("present_position") == 326  # one turn less
        robot.enable()
        np.testing.assert_allclose(robot.joint_positions().q[0], 0.5, atol=_tick(world, 0))
        robot.move_joints(np.array([-0.5, -0.3, 0.4, 0.1]))
        np.testing.assert_allclose(world.encoder_q()[0], -0.5, atol=_tick(world, 0))
    # Position Control Mode covers one turn: such a joint is refused there before anything moves
    world = World.default(model=model, seed=7, start=[-0.5, -0.3, 0.4, 0.1])
    emu, _ = robot_rig("dynamixel", world, ids=IDS, connect=False)
    with pytest.raises(Exception, match="crosses the 0/4095"):
        open_robot(f"{emu.url}&model={model}&latency=50")


# ---- Status Return Level ---------------------------------------------------------------------------------------
def test_status_return_level_below_2_is_honoured(robot_rig):
    """e-Manual, Status Return Level (68): 1 answers PING and READ only, 0 PING only. A servo left at 1 gets its
    writes without a status awaited (read back instead: no timeouts, no retries); one at 0 answers no read, so the
    driver sets it to 2 for this power-on and says so."""
    world = World.default(model="omx", seed=7, start=START)
    emu, _ = robot_rig("dynamixel", world, ids=IDS, status_return_level=1, connect=False)
    wire = Wire(emu)
    try:
        assert wire.write(12, 65, 1, 1)[0] == sdk.COMM_RX_TIMEOUT  # a write: no status
        assert wire.read(12, 65, 1) == 1  # a read: answered
        assert wire.write(12, SRL, 1, 0)[0] == sdk.COMM_RX_TIMEOUT
        g = sdk.GroupSyncRead(wire.port, wire.ph, PRESENT, 4)
        for i in IDS:
            g.addParam(i)
        assert g.txRxPacket() != sdk.COMM_SUCCESS  # level 0: not even a sync read
        assert wire.write(12, SRL, 1, 1)[0] == sdk.COMM_RX_TIMEOUT
    finally:
        wire.close()
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        _write_pose(robot, {"offset.j2": -0.01, "offset.j3": 0.01})
        robot.write_calibration({"offset.j2": -0.01, "offset.j3": 0.01})  # (it would time out awaiting a status)
        assert [emu.devices[i].get("homing_offset") for i in IDS] == [0, -7, 7, 0]
    world = World.default(model="omx", seed=7, start=START)
    emu, _ = robot_rig("dynamixel", world, ids=IDS, status_return_level=0, connect=False)
    log = _capture()
    with open_robot(f"{emu.url}&latency=20") as robot:  # each silent read: 4 x ~42 ms
        assert robot.joint_positions().q.shape == (4,)
    assert [emu.devices[i].get("status_return_level") for i in IDS] == [2] * 4
    said = [m for m in log.lines if "Status Return Level 0" in m]
    assert len(said) == 4 and all("\n" not in m for m in said)


class _capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []
        logging.getLogger("station").addHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


# ---- Fast Sync Read needs firmware that has it -------------------------------------------------------------------
def test_firmware_without_fast_sync_read_gets_sync_read(robot_rig):
    """Fast Sync Read (0x8A) exists from some firmware on (ROBOTIS-GIT/dynamixel_hardware_interface issues 79 and
    83, "FastSyncRead Rx Fail"; DynamixelSDK issue 527): older firmware does not answer it. The driver tries one
    at connect and uses the SDK's Sync Read from then on, said once."""
    world = World.default(model="omx", seed=7, start=START)
    emu, _ = robot_rig("dynamixel", world, ids=IDS, fast_sync_read=False, connect=False)
    log = _capture()
    with open_robot(f"{emu.url}&latency=20") as robot:  # each unanswered try: ~42 ms
        assert not robot.fast
        emu.reset_stats()
        robot.joint_positions()
        assert emu.stats["by_inst"] == {"sync_read": 1}
    said = [m for m in log.lines if "Fast Sync Read" in m]
    assert len(said) == 1 and "using Sync Read" in said[0]


# ---- the USB adapter's latency timer -----------------------------------------------------------------------------
@pytest.mark.parametrize("timer, warned", [(16, True), (1, False), (None, False)])
def test_latency_timer_above_2_ms_is_said_in_one_line(rig, tmp_path, timer, warned):
    """FTDI adapters default to a 16 ms latency timer (sysfs latency_timer); ROBOTIS recommend 1 ms. A fake sysfs
    root stands for the adapter; a pty has none: the timer is "unknown", nothing said."""
    from station.drivers.dynamixel.adapter import latency_timer_ms

    world, emu = rig
    name = Path(emu.path).name
    if timer is not None:
        d = tmp_path / "bus" / "usb-serial" / "devices" / name
        d.mkdir(parents=True)
        (d / "latency_timer").write_text(f"{timer}\n")
    assert latency_timer_ms(emu.path, tmp_path) == timer
    log = _capture()
    with open_robot(f"{emu.url}&latency=50", sysfs_root=str(tmp_path)) as robot:
        assert robot.adapter["latency_timer"] == ("unknown" if timer is None else f"{timer} ms")
    said = [m for m in log.lines if "latency timer" in m]
    assert len(said) == int(warned) and all("\n" not in m and "1 ms" in m for m in said)


# ---- power cycle -------------------------------------------------------------------------------------------------
def test_power_cycle_keeps_eeprom_loses_ram_and_drops_an_unsupported_arm(rig):
    """A power cycle of the servos: EEPROM (homing offset, drive mode) kept; RAM to its defaults (torque off,
    Status Return Level 2, Goal PWM at its limit); Present Position within one turn again; an arm that stood
    where gravity loads it falls, one parked where no joint carries load stays."""
    world, emu = rig
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        _write_pose(robot, {"offset.j3": 0.01})
        robot.write_calibration({"offset.j3": 0.01})
        robot.set_compliant(True)
        robot.set_compliant(False)
        robot.move_joints(np.array(START))
    emu.devices[12].set("status_return_level", 1)
    q0 = world.encoder_q().copy()
    emu.power_cycle()
    assert emu.devices[13].get("homing_offset") == 7 and not any(emu.devices[i].torque for i in IDS)
    assert emu.devices[12].get("status_return_level") == 2 and emu.power_cycles == 1
    assert abs(world.encoder_q()[1] - q0[1]) > 0.3  # no brake: the shoulder fell
    with open_robot(f"{emu.url}&latency=50") as robot:
        robot.enable()
        _write_pose(robot)  # parked where no joint carries load (None: every joint)
        q1 = world.encoder_q().copy()
    emu.power_cycle()
    assert np.max(np.abs(world.encoder_q() - q1)) <= max(_tick(world, j) for j in range(4))


def test_a_servo_not_in_a_position_mode_is_refused_before_motion(rig):
    """e-Manual, Operating Mode (11): velocity, current and PWM modes do not hold a position. The driver reads the
    mode at connect and refuses in one line (ConfigError) what it cannot drive: nothing moves, nothing is written.
    A Drive Mode bit the X430 does not have (1: dual-joint slave, X540 only) is a data range error."""
    world, emu = rig
    wire = Wire(emu)
    try:
        assert wire.write(12, OPERATING_MODE, 1, 1) == (sdk.COMM_SUCCESS, 0)
        assert wire.write(13, DRIVE_MODE, 1, 2) == (sdk.COMM_SUCCESS, 4)  # data range error
    finally:
        wire.close()
    q0 = world.encoder_q().copy()
    with pytest.raises(Exception, match=r"servo id 12 \(joint 2 shoulder\) is in operating mode 1 \(velocity") as e:
        open_robot(f"{emu.url}&latency=50")
    assert type(e.value).__name__ == "ConfigError" and "\n" not in str(e.value)
    assert np.array_equal(world.encoder_q(), q0) and not any(emu.devices[i].torque for i in IDS)
