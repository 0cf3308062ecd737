"""The emulated CiA 402 drives at protocol level: real canopen (RemoteNode/BaseNode402) and python-can
virtual buses, a sniffer bus on the same channel sees every frame on the wire."""

from __future__ import annotations

import time
import uuid

import can
import canopen
import pytest
from station.mocks.canopen import eds
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

SAVE, LOAD = eds.SAVE_SIGNATURE, eds.LOAD_SIGNATURE


@pytest.fixture
def rig(robot_rig):
    """The drives from robot_rig without the station's driver: the client here is python-canopen's own nodes (the
    emulator is what is tested, at protocol level), with a sniffer on the same channel."""
    world = World.default(model="arm6", seed=3)
    emu, _ = robot_rig("canopen", world, connect=False)
    chan = emu.channel
    sniff = can.Bus(interface="virtual", channel=chan)
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05  # quick teardown
    net.connect(interface="virtual", channel=chan)
    nodes = {}
    for i in (1, 2, 3):
        node = canopen.BaseNode402(i, str(eds.EDS_PATH))
        net.add_node(node)
        nodes[i] = node
    time.sleep(0.03)  # boot-up messages (5 ms after power-on)
    yield world, emu, net, nodes, sniff
    net.disconnect()
    sniff.shutdown()


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(0)) is not None:
        out.append(m)
    return out


def test_shipped_eds_matches_generator_and_loads():
    assert eds.EDS_PATH.read_text() == eds.generate(), "regenerate: python -m station.mocks.canopen.eds"
    od = canopen.import_od(str(eds.EDS_PATH), 5)
    assert od[0x1000].default == 0x00020192
    assert od[0x1800][1].default == 0x185  # $NODEID relative COB-ID
    for index in (0x6040, 0x6041, 0x6064, 0x607A, 0x60FD, 0x6060, 0x6061, 0x6081, 0x6071):
        assert od[index].pdo_mappable, hex(index)
    assert od[0x607C].storage_location == "PERSIST_APP"
    assert od[0x6502].default == eds.SUPPORTED_MODES


def test_identity_and_device_type_by_sdo(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[2]
    assert n.sdo[0x1000].raw & 0xFFFF == 402
    assert n.sdo[0x1008].raw == eds.DEVICE_NAME
    assert n.sdo[0x100A].raw == eds.SW_VERSION
    assert n.sdo[0x1018][1].raw == eds.VENDOR_ID
    assert n.sdo[0x1018][4].raw == emu.drives[2].serial


def test_bootup_after_nmt_reset_and_first_heartbeat_one_period_later(rig):
    world, emu, net, nodes, sniff = rig
    n = nodes[1]
    n.sdo[0x1017].raw = 50
    n.sdo[0x1010][1].raw = SAVE  # heartbeat time survives the reset
    drain(sniff)
    n.nmt.state = "RESET"
    n.nmt.wait_for_bootup(1.0)
    assert n.nmt.wait_for_heartbeat(1.0) == "PRE-OPERATIONAL"
    frames = [m for m in drain(sniff) if m.arbitration_id == 0x701]
    assert frames[0].data == bytearray([0x00])  # boot-up
    assert frames[1].data == bytearray([0x7F])  # first heartbeat: pre-operational
    gap = frames[1].timestamp - frames[0].timestamp
    assert 0.045 <= gap <= 0.2, gap


def test_402_state_machine_by_controlword(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[3]
    sw = lambda: n.sdo[0x6041].raw  # noqa: E731
    assert sw() & 0x4F == 0x40  # switch on disabled after power-up
    assert not world.enabled()[2]
    n.sdo[0x6040].raw = 0x06
    assert sw() & 0x6F == 0x21
    n.sdo[0x6040].raw = 0x07
    assert sw() & 0x6F == 0x23
    n.sdo[0x6040].raw = 0x0F
    assert sw() & 0x6F == 0x27 and world.enabled()[2]
    n.sdo[0x6040].raw = 0x02  # quick stop
    assert sw() & 0x6F == 0x07
    n.sdo[0x6040].raw = 0x0F  # transition 16 back to operation enabled
    assert sw() & 0x6F == 0x27
    n.sdo[0x6040].raw = 0x00  # disable voltage
    assert sw() & 0x4F == 0x40 and not world.enabled()[2]


def test_profile_position_move_in_the_homed_frame(rig):
    """Targets are in the 0x6064 frame: a drive whose homing added Z moves its joint to target - Z raw counts."""
    world, emu, net, nodes, _ = rig
    n = nodes[2]  # joint a2: gear 121, direction -1
    enc = world.nominal.joints[1].encoder
    _enable(n)
    n.sdo[0x607C].raw = n.sdo[0x6063].raw + 123456  # position reads this after homing: zero Z = 123456
    n.sdo[0x6098].raw = 37
    n.sdo[0x6060].raw = 6
    n.sdo[0x6040].raw = 0x1F  # homing start
    raw = enc.to_counts(world.encoder_q()[1])
    assert n.sdo[0x6064].raw == round(float(raw)) + 123456  # reported = raw + homing result
    n.sdo[0x6040].raw = 0x0F
    n.sdo[0x6060].raw = 1
    assert n.sdo[0x6061].raw == 1
    n.sdo[0x6081].raw = 500000
    target = n.sdo[0x6064].raw - 200000
    n.sdo[0x607A].raw = target
    n.sdo[0x6040].raw = 0x3F  # new set-point, change immediately
    assert n.sdo[0x6041].raw & (1 << 12)  # set-point acknowledged
    n.sdo[0x6040].raw = 0x0F
    assert n.sdo[0x6041].raw & (1 << 10)  # target reached (instant world)
    assert n.sdo[0x6064].raw == target
    assert world.encoder_q()[1] == pytest.approx(float(enc.to_si(target - 123456)), abs=1e-12)


def test_sync_and_event_timer_tpdos(rig):
    world, emu, net, nodes, sniff = rig
    for n in nodes.values():
        n.nmt.state = "OPERATIONAL"
    time.sleep(0.02)
    drain(sniff)
    for _ in range(5):
        net.sync.transmit()
        time.sleep(0.01)
    time.sleep(0.25)
    frames = drain(sniff)
    tpdo1 = [m for m in frames if 0x181 <= m.arbitration_id <= 0x183]
    assert len(tpdo1) == 5 * 3  # one TPDO1 per node per SYNC (transmission type 1)
    tpdo2 = [m for m in frames if 0x281 <= m.arbitration_id <= 0x283]
    # TPDO2 default: event timer 100 ms, ~0.3 s observed: 2..4 per node
    assert 6 <= len(tpdo2) <= 12, len(tpdo2)


def test_emcy_fault_and_reset_by_controlword_bit7(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[2]
    for cw in (0x06, 0x07, 0x0F):
        n.sdo[0x6040].raw = cw
    world.faults.inject("device_fault", device=2, code=0x4310)
    emcy = n.emcy.wait(timeout=1.0)
    assert emcy is not None and emcy.code == 0x4310
    assert n.sdo[0x6041].raw & 0x4F == 0x08  # FAULT
    assert n.sdo[0x603F].raw == 0x4310 and n.sdo[0x1001].raw != 0
    assert n.sdo[0x1003][1].raw == 0x4310
    assert world.joint_fault(1) == 0x4310 and not world.enabled()[1]
    n.sdo[0x6040].raw = 0x0F  # no effect in FAULT
    assert n.sdo[0x6041].raw & 0x4F == 0x08
    n.sdo[0x6040].raw = 0x80  # fault reset (rising edge of bit 7)
    assert n.sdo[0x6041].raw & 0x4F == 0x40
    assert world.joint_fault(1) is None
    deadline = time.monotonic() + 1.0
    while n.emcy.log[-1].code != 0 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert n.emcy.log[-1].code == 0x0000 and not n.emcy.active  # EMCY "error reset / no error"


def test_store_parameters_survive_reset_only_when_saved(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[1]
    with pytest.raises(canopen.SdoAbortedError):
        n.sdo[0x1010][1].raw = 0x12345678  # wrong signature: nothing stored
    n.sdo[0x607C].raw = -4242
    n.sdo[0x1010][3].raw = SAVE  # application parameters
    n.sdo[0x607C].raw = 777  # not saved
    emu.power_cycle([1])
    time.sleep(0.03)
    assert n.sdo[0x607C].raw == -4242
    n.sdo[0x1011][1].raw = LOAD  # restore defaults: effective after the next reset
    assert n.sdo[0x607C].raw == -4242
    n.nmt.state = "RESET"
    n.nmt.wait_for_bootup(1.0)
    assert n.sdo[0x607C].raw == 0


def test_store_file_keeps_parameters_across_emulator_restart(tmp_path):
    # its own rig: the drives restart on the same channel, as a power cycle leaves them on the same wire
    chan = f"t-{uuid.uuid4().hex[:8]}"
    store = tmp_path / "store.json"
    world = World.default(model="arm6")
    for value in (31337, None):
        emu = CanopenEmulator(world, channel=chan, store_path=store).start()
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05
        net.connect(interface="virtual", channel=chan)
        node = net.add_node(4, str(eds.EDS_PATH))
        try:
            time.sleep(0.02)
            if value is not None:
                node.sdo[0x607C].raw = value
                node.sdo[0x1010][1].raw = SAVE
            else:
                assert node.sdo[0x607C].raw == 31337
        finally:
            net.disconnect()
            emu.stop()


def test_pdo_mapping_is_validated(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[1]
    with pytest.raises(canopen.SdoAbortedError) as e:
        n.sdo[0x1A00][1].raw = 0x10000020  # 0x1000 device type is not mappable
    assert e.value.code == 0x06040041
    with pytest.raises(canopen.SdoAbortedError):
        n.sdo[0x1600][1].raw = 0x60410010  # statusword is read-only: not an RPDO object
    with pytest.raises(canopen.SdoAbortedError):
        n.sdo[0x6060].raw = 7  # interpolated position: not supported (0x6502)


def test_timeout_fault_silences_node(rig):
    world, emu, net, nodes, sniff = rig
    n = nodes[3]
    n.sdo[0x1017].raw = 20
    n.nmt.wait_for_heartbeat(1.0)
    world.faults.inject("timeout", device=3)
    time.sleep(0.05)
    drain(sniff)
    with pytest.raises(canopen.SdoCommunicationError):
        _ = n.sdo[0x1000].raw
    time.sleep(0.1)
    assert not [m for m in drain(sniff) if m.arbitration_id == 0x703]  # no heartbeat while silent
    assert nodes[2].sdo[0x1000].raw & 0xFFFF == 402  # the others still answer


def _enable(n) -> None:
    for cw in (0x06, 0x07, 0x0F):
        n.sdo[0x6040].raw = cw


def test_software_limit_clamps_and_relative_setpoint(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[1]
    _enable(n)
    n.sdo[0x6060].raw = 1
    here = n.sdo[0x6064].raw
    n.sdo[0x607D][1].raw = here - 1000
    n.sdo[0x607D][2].raw = here + 1000
    n.sdo[0x607A].raw = here + 5000
    n.sdo[0x6040].raw = 0x3F
    assert n.sdo[0x6041].raw & (1 << 11)  # internal limit active
    n.sdo[0x6040].raw = 0x0F
    assert n.sdo[0x6064].raw == here + 1000
    n.sdo[0x607A].raw = -300
    n.sdo[0x6040].raw = 0x7F  # relative (bit 6)
    n.sdo[0x6040].raw = 0x4F
    assert n.sdo[0x6064].raw == here + 700 and not n.sdo[0x6041].raw & (1 << 11)


def test_synchronous_rpdo_acts_on_the_next_sync(rig):
    world, emu, net, nodes, _ = rig
    n = nodes[2]
    _enable(n)
    n.sdo[0x6060].raw = 1
    n.sdo[0x1400][2].raw = 1  # RPDO1 synchronous
    n.nmt.state = "OPERATIONAL"
    n.rpdo.read()
    here = n.sdo[0x6064].raw
    n.rpdo[1][0x607A].raw = here + 20000
    n.rpdo[1][0x6040].raw = 0x3F
    n.rpdo[1].transmit()
    time.sleep(0.05)
    assert n.sdo[0x6064].raw == here  # buffered until SYNC
    net.sync.transmit()
    time.sleep(0.05)
    assert n.sdo[0x6064].raw == here + 20000


def test_profile_velocity_mode_moves_a_realtime_joint(robot_rig):
    world = World.default(model="arm6", time_mode="realtime")
    emu, _ = robot_rig("canopen", world, connect=False)
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.connect(interface="virtual", channel=emu.channel)
    try:
        time.sleep(0.02)
        n = net.add_node(4, str(eds.EDS_PATH))
        _enable(n)
        n.sdo[0x6060].raw = 3
        q0 = world.encoder_q()[3]
        enc = world.nominal.joints[3].encoder  # direction -1: positive counts = negative joint motion
        n.sdo[0x60FF].raw = int(0.5 * enc.counts_per_unit * enc.gear)  # 0.5 rad/s at the joint
        time.sleep(0.3)
        assert world.encoder_q()[3] < q0 - 0.05
        n.sdo[0x60FF].raw = 0
        time.sleep(0.2)
        assert not world.is_moving()
    finally:
        net.disconnect()
