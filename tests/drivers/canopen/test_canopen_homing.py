"""Home offset, homing and the store (CiA 402 0x607C / homing mode 6, CiA 301 0x1010) as the vendors document
them, and the driver's write-back against it: a new zero takes effect only through a homing, the driver proves it
by the reported position at the same physical pose, stores only application parameters, and refuses an
unreferenced (incremental) encoder before anything moves. Truth: the world's encoder and the emulated drives'
object dictionaries; real canopen + python-can on both sides."""

from __future__ import annotations

import time
import uuid

import can
import canopen
import numpy as np
import pytest
from station.mocks.canopen import eds
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

from station.robot import ConfigError, DeviceFault, open_robot

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]
SAVE = eds.SAVE_SIGNATURE


def count(world, i: int) -> float:
    """One encoder count of joint ``i`` in SI."""
    enc = world.nominal.joints[i].encoder
    return 1.0 / abs(enc.counts_per_unit * enc.gear)


@pytest.fixture
def raw():
    """Emulated drives and a plain canopen client (a commissioning tool), no station driver."""
    chan = f"h-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=3, start=START)
    emu = CanopenEmulator(world, channel=chan).start()
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.connect(interface="virtual", channel=chan)
    node = canopen.BaseNode402(2, str(eds.EDS_PATH))
    net.add_node(node)
    time.sleep(0.03)
    yield world, emu, node
    net.disconnect()
    emu.stop()


def _enable(n) -> None:
    for cw in (0x06, 0x07, 0x0F):
        n.sdo[0x6040].raw = cw


def test_home_offset_takes_effect_only_when_homing_completes(raw):
    """CiA 402 0x607C (Elmo MAN-CAN402IG 9.2: "The zero position is determined after a successful homing
    sequence"): writing and even storing it changes nothing; homing mode 6 with method 37 (current position) sets
    0x6064 to the home offset at the present pose, with statusword bits 12 (attained) and 10 set, bit 13 clear;
    0x6063 (the encoder) is untouched, and the joint does not move."""
    world, emu, n = raw
    p0, i0, q0 = n.sdo[0x6064].raw, n.sdo[0x6063].raw, world.encoder_q().copy()
    n.sdo[0x607C].raw = p0 + 5000
    assert n.sdo[0x6064].raw == p0
    n.sdo[0x1010][3].raw = SAVE
    emu.power_cycle([2])
    time.sleep(0.03)
    assert n.sdo[0x607C].raw == p0 + 5000 and n.sdo[0x6064].raw == p0  # stored, still not applied
    _enable(n)
    with pytest.raises(canopen.SdoAbortedError):
        n.sdo[0x6098].raw = 1  # a switch-based method: not this drive's (35/37 only)
    n.sdo[0x6098].raw = 37
    n.sdo[0x6060].raw = 6
    sw = n.sdo[0x6041].raw
    assert not sw & (1 << 12) or True  # absolute encoder: referenced from power-up
    n.sdo[0x6040].raw = 0x1F  # rising edge of bit 4: start homing
    sw = n.sdo[0x6041].raw
    assert sw & (1 << 12) and sw & (1 << 10) and not sw & (1 << 13)
    assert n.sdo[0x6064].raw == p0 + 5000 and n.sdo[0x6063].raw == i0
    assert np.array_equal(world.encoder_q(), q0)


def test_homing_without_a_method_is_a_homing_error(raw):
    world, emu, n = raw
    _enable(n)
    p0 = n.sdo[0x6064].raw
    n.sdo[0x607C].raw = p0 + 777
    n.sdo[0x6060].raw = 6  # 0x6098 is 0: no method assigned
    n.sdo[0x6040].raw = 0x1F
    sw = n.sdo[0x6041].raw
    assert sw & (1 << 13) and not sw & (1 << 12)
    assert n.sdo[0x6064].raw == p0


def test_save_all_only_in_switch_on_disabled(raw):
    """Yaskawa Sigma-7 (SGD7S manual 15.2, 1010h): sub-indices 1 and 4 only in SWITCH ON DISABLED; sub 3 any
    time. A wrong signature is refused (CiA 301: abort 0800 002xh)."""
    world, emu, n = raw
    _enable(n)
    with pytest.raises(canopen.SdoAbortedError) as e:
        n.sdo[0x1010][1].raw = SAVE
    assert e.value.code == 0x08000022
    n.sdo[0x1010][3].raw = SAVE
    with pytest.raises(canopen.SdoAbortedError):
        n.sdo[0x1010][3].raw = 0x12345678


# ---- the driver's write-back ------------------------------------------------------------------------------
@pytest.fixture
def arm():
    chan = f"w-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=7, start=START)
    emu = CanopenEmulator(world, channel=chan).start()
    url = f"canopen+virtual://{chan}?nodes=1-6&model=arm6"
    robot = open_robot(url)
    yield world, emu, robot, url
    robot.close()
    emu.stop()


def test_write_back_changes_the_reported_position_by_the_offset_at_the_same_pose(arm):
    """The new zero takes effect: at the same physical pose (the world's encoder unchanged) each joint reads
    exactly the change of its offset more, now and after a power cycle of the drives."""
    world, emu, robot, url = arm
    before = robot.joint_positions().q
    q_raw = world.encoder_q().copy()
    change = {"offset.j2": 0.0123, "offset.j3": -0.004, "offset.j6": 0.5}
    robot.write_calibration(change)
    assert np.array_equal(world.encoder_q(), q_raw)  # nothing moved
    after = robot.joint_positions().q
    for i in range(6):
        want = change.get(f"offset.j{i + 1}", 0.0)
        assert abs(after[i] - before[i] - want) <= 1.5 * count(world, i), (i, after[i] - before[i], want)
    robot.close()
    emu.power_cycle()
    time.sleep(0.05)
    with open_robot(url) as again:
        assert np.all(np.abs(again.joint_positions().q - after) <= 1.5 * np.array([count(world, i)
                                                                                  for i in range(6)]))
        back = again.read_calibration()
    assert all(abs(back[k] - v) <= count(world, int(k[-1]) - 1) for k, v in change.items())


def test_the_other_home_offset_convention_is_found_and_handled():
    """CiA 402's text ("the zero position is offset from the home position by adding the home offset": 0x6064 =
    -0x607C at the home position; Elmo, Parker, Applied Motion quote it) against the vendors that set 0x6064 to
    the home offset (Nanotec, KEB): the driver sees which after the first homing and homes again."""
    chan = f"w-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=7, start=START, buses={"canopen": {"home_offset": "zero"}})
    with CanopenEmulator(world, channel=chan) as emu, open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6") \
            as robot:
        before = robot.joint_positions().q
        robot.write_calibration({"offset.j2": 0.02, "offset.j5": -0.01})
        d = robot.joint_positions().q - before
        assert abs(d[1] - 0.02) <= 1.5 * count(world, 1) and abs(d[4] + 0.01) <= 1.5 * count(world, 4)
        assert robot.home_signs == {2: -1, 5: -1}
        assert emu.drives[2].home_offset == -emu.drives[2].position_actual()  # the CiA reading of 0x607C


def test_a_write_back_that_changes_nothing_is_a_failure(arm):
    """A drive whose homing completes but ignores its home offset: the reported position at the same pose does
    not change, which the driver calls a failure (one line), and nothing is stored."""
    world, emu, robot, url = arm
    d = emu.drives[3]
    d._home = lambda: setattr(d, "referenced", True)  # firmware that signals "attained" and applies nothing
    with pytest.raises(DeviceFault, match="node 3.*did not change") as e:
        robot.write_calibration({"offset.j3": 0.01})
    assert "\n" not in str(e.value)
    assert (eds.POSITION_OFFSET, 0) not in d.stored


def test_store_keeps_the_calibration_and_nothing_of_the_stations_own(arm):
    """0x1010:03 (application parameters) after the homing: the zero survives a power cycle; the station's PDO
    layout, heartbeat settings, homing method and lost-station reaction do not (volatile, or put back as found
    before the store)."""
    world, emu, robot, url = arm
    d = emu.drives[2]
    assert d.get(0x1017) == 100 and d.consumers()  # what the station configured at connect
    robot.write_calibration({"offset.j2": 0.01})
    robot.close()
    emu.power_cycle()
    time.sleep(0.05)
    d = emu.drives[2]
    assert d.get(0x1017) == 0 and not d.consumers()
    assert [d.get(0x1A00, k) for k in range(0, 4)] == [3, 0x60410010, 0x60640020, 0x60610008]  # EDS default
    assert d.get(0x1800, 2) == 1 and d.get(0x1801, 5) == 100
    assert d.get(0x6098) == 0 and d.get(0x6007) == 0 and d.get(0x6081) == 0
    direction = world.nominal.joints[1].encoder.direction
    assert d.position_offset != 0 and abs(direction * d.position_offset * count(world, 1) - 0.01) <= count(world, 1)


def test_interrupted_store_is_volatile_and_resent_by_persist(arm):
    """Homed but not stored: the zero is volatile (lost at a power cycle); ``persist_calibration`` stores it."""
    world, emu, robot, url = arm
    real = robot.bus.store_parameters
    robot.bus.store_parameters = lambda node_id: None  # killed before the store
    robot.write_calibration({"offset.j4": 0.02})
    robot.bus.store_parameters = real
    assert abs(robot.read_calibration()["offset.j4"] - 0.02) <= count(world, 3)
    robot.close()
    emu.power_cycle()
    time.sleep(0.05)
    with open_robot(url) as again:
        assert again.read_calibration()["offset.j4"] == 0.0
        again.write_calibration({"offset.j4": 0.02})
        assert again.persist_calibration() == again.nodes
    emu.power_cycle()
    time.sleep(0.05)
    with open_robot(url) as again:
        assert abs(again.read_calibration()["offset.j4"] - 0.02) <= count(world, 3)


# ---- multi-turn: incremental encoders -----------------------------------------------------------------------
def test_incremental_encoder_is_refused_before_anything_moves():
    """Kinco FD: the multi-turn position needs a battery (or an absolute encoder); an incremental encoder powers
    up counting from 0 where the joint stands (0x6063 = 0) and reads wrong by whole motor turns / gear. The
    driver finds it unreferenced (homing mode, statusword bit 12) and refuses in one line, sending no RPDO; with
    ``encoder=absolute`` declared it connects; once homed, it is referenced."""
    chan = f"i-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=3, start=START, buses={"canopen": {"incremental": [3]}})
    with CanopenEmulator(world, channel=chan) as emu:
        assert emu.drives[3].internal_value() == 0 and emu.drives[2].internal_value() != 0
        url = f"canopen+virtual://{chan}?nodes=1-6&model=arm6"
        sniff = can.Bus(interface="virtual", channel=chan)
        try:
            with pytest.raises(ConfigError, match=r"node\(s\) \[3\].*not referenced.*home.*encoder=absolute") as e:
                open_robot(url)
            assert "\n" not in str(e.value)
            frames = []
            while (m := sniff.recv(0)) is not None:
                frames.append(m)
            rpdo1 = [m for m in frames if 0x201 <= m.arbitration_id <= 0x206 or 0x401 <= m.arbitration_id <= 0x406]
            assert not rpdo1  # no controlword, no target: nothing could move
        finally:
            sniff.shutdown()
        with open_robot(url + "&encoder=absolute") as robot:
            assert robot.joint_positions().q[2] == pytest.approx(world.encoder_q()[2] - START[2], abs=1e-6)
            robot.enable()
            robot.write_calibration({"offset.j3": START[2]})  # homing on the current position: referenced now
        with open_robot(url) as robot:
            assert robot.joint_positions().q[2] == pytest.approx(world.encoder_q()[2], abs=2 * count(world, 2))
        emu.power_cycle()
        time.sleep(0.05)
        with pytest.raises(ConfigError, match="not referenced"):
            open_robot(url)  # an incremental encoder forgets its homing at power-off
