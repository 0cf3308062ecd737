"""The CiA 402 driver against the emulated drives and the real simulated world, over python-can's virtual
bus (real canopen and python-can on both sides). Ground truth comes from the world, never the driver."""

from __future__ import annotations

import time
import uuid

import can
import numpy as np
import pytest
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

from station.robot import ConfigError, ConnectionLost, LimitError, SafetyStop, open_robot
from station.robot.protocol import Robot

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]


def quantum(model) -> np.ndarray:
    """Half an encoder count per joint, SI: the resolution of every readout."""
    return np.array([0.5 / (j.encoder.counts_per_unit * j.encoder.gear) for j in model.joints]) + 1e-12


@pytest.fixture
def cell(robot_rig):
    world = World.default(model="arm6", seed=7, start=START)
    emu, robot = robot_rig("canopen", world, enable=False)
    return world, emu, robot, emu.channel


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(0)) is not None:
        out.append(m)
    return out


def test_fulfils_robot_protocol_and_identity(cell):
    world, emu, robot, chan = cell
    assert isinstance(robot, Robot)
    ident = robot.identity()
    assert ident.model == "arm6"
    assert [d["node"] for d in ident.devices] == [1, 2, 3, 4, 5, 6]
    assert [d["serial"] for d in ident.devices] == [emu.drives[i].serial for i in range(1, 7)]
    assert ident.serial.endswith(f"{emu.drives[1].serial:08X}")
    assert ident.firmware == "1.2.0"


def test_readout_equals_truth_through_gear_and_direction(cell):
    world, emu, robot, chan = cell
    snap = robot.joint_positions()
    truth = world.encoder_q()
    assert snap.raw_unit == "count"
    for i, j in enumerate(world.nominal.joints):
        assert snap.raw[i] == round(float(j.encoder.to_counts(truth[i])))  # counts incl. gear and sign
    assert np.all(np.abs(snap.q - truth) <= quantum(world.nominal))
    assert np.any(np.array([j.encoder.direction for j in world.nominal.joints]) < 0)
    # the true tip follows from the readout through the true model
    assert np.linalg.norm(world.truth.position(snap.q) - world.tip_true()) < 2e-6


def test_move_reaches_target_and_jog(cell):
    world, emu, robot, chan = cell
    robot.enable()
    assert robot.status().enabled and all(world.enabled())
    target = np.array([0.1, -0.4, 0.6, 0.2, 0.3, -0.2])
    robot.move_joints(target, speed=0.5)
    assert np.all(np.abs(world.encoder_q() - target) <= quantum(world.nominal))
    assert np.all(np.abs(robot.joint_positions().q - target) <= 2 * quantum(world.nominal))
    robot.jog("joint", 3, 0.05, speed=0.2)
    assert world.encoder_q()[3] == pytest.approx(0.25, abs=2 * quantum(world.nominal)[3])
    p0 = world.nominal.position(robot.joint_positions().q)
    robot.jog("cartesian", 2, 0.005, speed=0.05)
    p1 = world.nominal.position(robot.joint_positions().q)
    assert p1 - p0 == pytest.approx([0, 0, 0.005], abs=5e-6)


def test_limits_refuse_and_nothing_is_sent(cell):
    world, emu, robot, chan = cell
    robot.enable()
    sniff = can.Bus(interface="virtual", channel=chan)
    try:
        before = world.encoder_q()
        bad = np.array(START)
        bad[1] = np.radians(75)  # a2 limit is +60 deg
        with pytest.raises(LimitError, match="a2"):
            robot.move_joints(bad)
        with pytest.raises(LimitError):
            robot.move_joints(np.array(START), speed=float("nan"))
        with pytest.raises(LimitError):
            robot.jog("cartesian", 0, 0.01, speed=0.5)  # above the 0.25 m/s manual tool-speed cap
        with pytest.raises(LimitError):
            robot.jog("joint", 1, np.radians(200))
        rpdo_ids = {base + node for base in (0x200, 0x300, 0x400, 0x500) for node in range(1, 7)}
        rpdos = [m for m in drain(sniff) if m.arbitration_id in rpdo_ids or 0x600 < m.arbitration_id < 0x680]
        assert rpdos == []
        assert np.array_equal(world.encoder_q(), before)
    finally:
        sniff.shutdown()


def test_streaming_uses_no_sdo_and_one_tpdo_per_node(cell):
    world, emu, robot, chan = cell
    sniff = can.Bus(interface="virtual", channel=chan)
    try:
        robot.joint_positions()
        drain(sniff)
        n = 30
        for _ in range(n):
            robot.joint_positions()
        frames = drain(sniff)
    finally:
        sniff.shutdown()
    sdo = [m for m in frames if 0x580 <= m.arbitration_id < 0x680]
    assert sdo == []
    syncs = sum(m.arbitration_id == 0x80 for m in frames)
    tpdo1 = sum(0x181 <= m.arbitration_id <= 0x186 for m in frames)
    assert syncs >= n and tpdo1 >= 6 * n - 6
    assert abs(tpdo1 - 6 * syncs) <= 12  # one TPDO1 per node per SYNC


def test_calibration_write_back_round_trip_and_power_cycle(cell):
    world, emu, robot, chan = cell
    assert robot.read_calibration() == {f"offset.j{i}": 0.0 for i in range(1, 7)}
    q_raw = world.encoder_q()
    values = {"offset.j2": 0.0123, "offset.j4": -0.0201, "offset.j6": 0.5}
    robot.write_calibration(values)
    back = robot.read_calibration()
    for name, v in values.items():
        i = int(name[-1]) - 1
        assert back[name] == pytest.approx(v, abs=quantum(world.nominal)[i] * 2)
    q_new = robot.joint_positions().q
    expect = q_raw.copy()
    for name, v in values.items():
        expect[int(name[-1]) - 1] += v
    assert np.all(np.abs(q_new - expect) <= 3 * quantum(world.nominal))  # q_new = q_raw + value
    assert np.array_equal(world.encoder_q(), q_raw)  # writing offsets never moves the arm
    robot.close()
    emu.power_cycle()
    time.sleep(0.05)
    again = open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6")
    try:
        assert again.read_calibration() == back
        assert np.all(np.abs(again.joint_positions().q - expect) <= 3 * quantum(world.nominal))
    finally:
        again.close()


def test_write_calibration_rejects_bad_input(cell):
    world, emu, robot, chan = cell
    with pytest.raises(ConfigError, match="offset.j9"):
        robot.write_calibration({"offset.j9": 0.1})
    with pytest.raises(ConfigError, match="finite"):
        robot.write_calibration({"offset.j1": float("inf")})
    assert robot.read_calibration()["offset.j1"] == 0.0


def test_touch_on_needle_and_compliant_seating_in_socket(cell):
    world, emu, robot, chan = cell
    robot.enable()
    assert robot.touch() is False
    q_needle = world.truth.ik(world.points["N"].position, np.array([0, -0.5, 0.5, 0, 0.5, 0]),
                              position_only=True).q[0]
    robot.move_joints(q_needle, speed=1.0)
    assert world.contact() and robot.touch() is True
    # near the socket (3 mm above its centre, inside the capture radius) then compliant: it seats
    above = world.points["A"].position + np.array([0, 0, 0.003])
    q_above = world.truth.ik(above, q_needle, position_only=True).q[0]
    robot.move_joints(q_above, speed=1.0)
    assert robot.touch() is False
    robot.set_compliant(True)
    assert world.compliant and robot.status().compliant
    assert world.seated == "A" and robot.touch() is True
    with pytest.raises(SafetyStop, match="compliant"):
        robot.move_joints(q_above)
    seated_q = world.encoder_q()
    robot.set_compliant(False)
    assert not world.compliant and not robot.status().compliant
    assert np.all(np.abs(robot.joint_positions().q - seated_q) <= quantum(world.nominal))  # holds where it sat


def test_stop_halts_a_realtime_move(robot_rig):
    world = World.default(model="arm6", seed=7, start=START, time_mode="realtime")
    _, robot = robot_rig("canopen", world)
    target = np.array(START) + 0.3
    robot.move_joints(target, speed=0.5, wait=False)
    time.sleep(0.1)
    assert world.is_moving()
    robot.stop()
    time.sleep(0.5)
    assert not world.is_moving()
    assert np.max(np.abs(world.encoder_q() - target)) > 0.05  # stopped short of the target
    assert robot.status().enabled  # halt keeps the drives enabled
    robot.move_joints(target, speed=1.0)  # and a new move clears the halt
    assert np.all(np.abs(world.encoder_q() - target) <= quantum(world.nominal))


def test_url_errors():
    with pytest.raises(ConfigError, match="model"):
        open_robot("canopen+virtual://x?nodes=1-6")
    with pytest.raises(ConfigError, match="one node per joint"):
        open_robot("canopen+virtual://x?nodes=1-3&model=arm6")
    with pytest.raises(ConfigError, match="unknown option"):
        open_robot("canopen+virtual://x?nodes=1-6&model=arm6&bitrat=5")
    t = time.monotonic()
    with pytest.raises(ConnectionLost, match="cannot open"):
        open_robot("canopen+socketcand://127.0.0.1:9?channel=can0&nodes=1-6&model=arm6")
    assert time.monotonic() - t < 3


def test_virtual_channel_name_keeps_its_case():
    # its own rig: the channel's name, with capitals, is what is tested (robot_rig names its channels)
    chan = f"Cell-{uuid.uuid4().hex[:6].upper()}"
    with CanopenEmulator(World.default(model="arm6"), channel=chan):
        robot = open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6")
        robot.close()


def test_no_drives_on_the_bus_is_connection_lost():
    chan = f"d-{uuid.uuid4().hex[:8]}"
    with pytest.raises(ConnectionLost, match="node 1 .*does not answer"):
        open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6")


def test_enable_switches_all_drives_together_and_resets_faults(cell):
    """All six drives walk the CiA 402 power state machine in the same SYNC rounds (3 transitions: a handful
    of rounds, not 3 per drive one after another), and a drive in FAULT is reset on the way."""
    world, emu, robot, chan = cell
    emu.drives[4].fault(0x4310)
    t0 = time.monotonic()
    while not robot.status().faults and time.monotonic() - t0 < 1.0:
        time.sleep(0.01)
    # every state entry on the device side, in order: "together" is an order, not a frame count (the count of
    # SYNC rounds grows with the host's load, the order does not)
    entries: list[tuple[int, str]] = []
    for n, drive in emu.drives.items():
        enter = drive._enter
        drive._enter = lambda new, n=n, enter=enter: (entries.append((n, new)), enter(new))[1]
    robot.enable()
    st = robot.status()
    assert st.enabled and not st.faults
    assert all(emu.drives[n].state == "OPERATION ENABLED" for n in range(1, 7))
    first_oe = next(i for i, (_, new) in enumerate(entries) if new == "OPERATION ENABLED")
    started = {n for n, _ in entries[:first_oe]}
    assert started == set(range(1, 7)), entries  # one after another: drive 1 enabled before drive 2 started
    target = np.array(START) + 0.05
    robot.move_joints(target, speed=1.0)
    assert np.max(np.abs(world.encoder_q() - target)) < 1e-5


def test_touch_right_after_a_move_is_read_after_the_move(cell):
    """The contact TPDO is event-timed (touch_ms): a reading from before the last command is never reused, even
    a young one (instant world: the move onto the needle takes a few SYNC rounds, less than one event period)."""
    world, emu, robot, chan = cell
    robot.enable()
    guess = np.array([0, -0.5, 0.5, 0, 0.5, 0])
    q_needle = world.truth.ik(world.points["N"].position, guess, position_only=True).q[0]
    q_off = world.truth.ik(world.points["N"].position + np.array([0, 0, 0.01]), q_needle, position_only=True).q[0]
    robot.move_joints(q_off, speed=1.0)
    for _ in range(3):
        assert robot.touch() is False  # the newest reading is fresh and cached
        robot.move_joints(q_needle, speed=2.0)
        assert world.contact() and robot.touch() is True
        robot.move_joints(q_off, speed=2.0)
        assert not world.contact() and robot.touch() is False


def test_sdo_timeout_ms_is_the_answer_time_of_every_sdo():
    """``sdo_timeout_ms`` is what an unanswered SDO waits: a bus without drives fails after about that long
    (python-canopen makes one retry: 2 x the time), never sooner."""
    for ms in (50, 1500):
        chan = f"d-{uuid.uuid4().hex[:8]}"
        t = time.monotonic()
        with pytest.raises(ConnectionLost, match="node 1 .*does not answer"):
            open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6&sdo_timeout_ms={ms}")
        took = time.monotonic() - t
        assert took >= ms / 1000.0, (ms, took)
        if ms == 50:
            assert took < 1.5, took  # the 1.5 s setting is not a floor the short one also waits
    with pytest.raises(ConfigError, match="sdo_timeout_ms"):
        open_robot("canopen+virtual://x?nodes=1-6&model=arm6&sdo_timeout_ms=5")


def test_store_waits_for_a_drive_writing_its_flash(cell):
    """A real drive answers "store parameters" (0x1010) after writing its flash, longer than an ordinary SDO
    answer: the write-back waits for it (at the default 300 ms SDO time) instead of calling the drive lost."""
    world, emu, robot, chan = cell
    emu.store_s = 0.8  # the emulated flash write: each drive answers the store 0.8 s late
    values = {"offset.j1": 0.01, "offset.j3": -0.02}
    t = time.monotonic()
    robot.write_calibration(values)
    assert time.monotonic() - t >= 2 * 0.8  # both stores were answered late, and waited for
    emu.store_s = 0.0
    back = robot.read_calibration()
    for name, v in values.items():
        assert back[name] == pytest.approx(v, abs=2 * float(quantum(world.nominal).max()))
    assert robot.persist_calibration() == robot.nodes
