"""Dynamixel emulator at the protocol level: the real dynamixel_sdk talks to it over a pty."""

from __future__ import annotations

import os
import threading
import time

import dynamixel_sdk as sdk
import numpy as np
import pytest
from station.drivers.dynamixel.bus import DxlPort
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.dynamixel import packets as pk
from station.mocks.world import World

IDS = [11, 12, 13, 14]


@pytest.fixture()
def bus():
    world = World.default(model="omx", seed=3, start=[0.1, -0.2, 0.3, -0.4])
    emu = DynamixelEmulator(world, ids=IDS)
    path = emu.start().path
    port = DxlPort(path, latency_ms=50)  # the SDK's PortHandler, timeout margin for a loaded host
    assert port.openPort() and port.setBaudRate(1_000_000)
    ph = sdk.PacketHandler(2.0)
    yield world, emu, port, ph
    port.closePort()
    emu.stop()


def test_crc_matches_the_sdk_and_the_spec_example():
    ph = sdk.PacketHandler(2.0)
    rng = np.random.default_rng(1)
    for n in (1, 7, 64, 300):
        data = bytes(rng.integers(0, 256, n, dtype=np.uint8))
        assert pk.crc16(data) == ph.updateCRC(0, list(data), n)
    # e-manual example: ping to ID 1 is FF FF FD 00 01 03 00 01 19 4E
    assert pk.build(1, 0x01) == bytes.fromhex("FFFFFD0001030001194E")


def test_stuffing_round_trip_and_parser_resyncs_after_garbage():
    body = bytes([0x03, 0xFF, 0xFF, 0xFD, 0x00, 0xFF, 0xFF, 0xFD])
    stuffed = pk.stuff(body)
    assert stuffed.count(b"\xff\xff\xfd\xfd") == 2 and pk.unstuff(stuffed) == body
    frame = pk.build(7, body[0], body[1:])
    p = pk.StreamParser()
    got = p.feed(b"\x00\xff\x12" + frame[:5]) + p.feed(frame[5:] + frame)
    assert [(g.dxl_id, g.inst, g.params, g.crc_ok) for g in got] == [(7, 0x03, body[1:], True)] * 2
    assert p.dropped == 3
    bad = bytearray(frame)
    bad[-1] ^= 0xFF
    assert p.feed(bytes(bad))[0].crc_ok is False


def test_ping_read_write_and_unknown_id(bus):
    world, emu, port, ph = bus
    assert ph.ping(port, 11) == (1020, sdk.COMM_SUCCESS, 0)
    assert ph.ping(port, 200)[:2] == (0x5A01, sdk.COMM_SUCCESS)  # the contact sensor device
    assert ph.ping(port, 99)[1] == sdk.COMM_RX_TIMEOUT
    fw, res, _ = ph.read1ByteTxRx(port, 12, 6)
    assert res == sdk.COMM_SUCCESS and fw == 46
    ticks, res, err = ph.read4ByteTxRx(port, 13, 132)
    enc = world.nominal.joints[2].encoder
    assert (res, err) == (sdk.COMM_SUCCESS, 0)
    assert ticks == round(float(enc.to_counts(world.encoder_q()[2])))


def test_access_rules_status_errors(bus):
    world, emu, port, ph = bus
    assert ph.write1ByteTxRx(port, 11, 64, 1) == (sdk.COMM_SUCCESS, 0)
    # EEPROM (homing offset) is locked while torque is on: access error 7
    assert ph.write4ByteTxRx(port, 11, 20, 100) == (sdk.COMM_SUCCESS, 7)
    # read-only item: access error; value out of range: data range error 4; half an item: length error 5
    assert ph.write4ByteTxRx(port, 11, 132, 5)[1] == 7
    assert ph.write1ByteTxRx(port, 11, 65, 9)[1] == 4
    assert ph.write2ByteTxRx(port, 11, 116, 5)[1] == 5
    # goal outside the position limits in position mode: data limit error 6
    assert ph.write4ByteTxRx(port, 11, 116, 5000)[1] == 6
    # unknown instruction: instruction error 2 (frame built by our codec, answer parsed by the SDK)
    port.clearPort()
    port.writePort(pk.build(11, 0x7E))
    port.setPacketTimeout(11)
    rx, res = ph.rxPacket(port, False)
    assert res == sdk.COMM_SUCCESS and rx[4] == 11 and rx[8] == 2


def test_byte_stuffing_on_the_wire_with_the_sdk(bus):
    world, emu, port, ph = bus
    value = int.from_bytes(b"\xff\xff\xfd\xff", "little", signed=True)  # -131073: within the homing range
    assert ph.write4ByteTxRx(port, 12, 20, value & 0xFFFFFFFF) == (sdk.COMM_SUCCESS, 0)
    got, res, err = ph.read4ByteTxRx(port, 12, 20)
    assert (res, err) == (sdk.COMM_SUCCESS, 0)
    assert got - (1 << 32) == value
    assert emu.stats["bad_crc"] == 0


def test_sync_fast_bulk_read_and_writes(bus):
    world, emu, port, ph = bus
    enc = [j.encoder for j in world.nominal.joints]
    expect = [round(float(e.to_counts(q))) for e, q in zip(enc, world.encoder_q(), strict=True)]
    g = sdk.GroupSyncRead(port, ph, 132, 4)
    for i in IDS:
        g.addParam(i)
    assert g.txRxPacket() == sdk.COMM_SUCCESS
    assert [g.getData(i, 132, 4) for i in IDS] == expect
    assert g.fastSyncRead() == sdk.COMM_SUCCESS
    assert [g.getData(i, 132, 4) for i in IDS] == expect
    # sync write torque on, bulk write goal on one servo + LED on another, bulk read both back
    sw = sdk.GroupSyncWrite(port, ph, 64, 1)
    for i in IDS:
        sw.addParam(i, [1])
    assert sw.txPacket() == sdk.COMM_SUCCESS
    bw = sdk.GroupBulkWrite(port, ph)
    bw.addParam(11, 116, 4, list((expect[0] + 100).to_bytes(4, "little")))
    bw.addParam(12, 65, 1, [1])
    assert bw.txPacket() == sdk.COMM_SUCCESS
    br = sdk.GroupBulkRead(port, ph)
    br.addParam(11, 132, 4)
    br.addParam(12, 65, 1)
    assert br.txRxPacket() == sdk.COMM_SUCCESS
    assert br.getData(11, 132, 4) == expect[0] + 100  # instant world: the move is done
    assert br.getData(12, 65, 1) == 1
    fb = sdk.GroupBulkRead(port, ph)
    fb.addParam(13, 132, 4)
    fb.addParam(200, 128, 1)  # the contact sensor answers in the same fast bulk read
    assert fb.fastBulkRead() == sdk.COMM_SUCCESS
    assert fb.getData(13, 132, 4) == expect[2] and fb.getData(200, 128, 1) == int(world.contact())
    assert abs(world.encoder_q()[0] - enc[0].to_si(expect[0] + 100)) < 1e-9


def test_reg_write_action_and_reboot(bus):
    world, emu, port, ph = bus
    assert ph.write1ByteTxRx(port, 13, 64, 1) == (sdk.COMM_SUCCESS, 0)
    start = ph.read4ByteTxRx(port, 13, 132)[0]
    assert ph.regWriteTxRx(port, 13, 116, 4, list((start - 200).to_bytes(4, "little"))) == (sdk.COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 13, 69)[0] == 1  # registered instruction pending
    assert ph.read4ByteTxRx(port, 13, 132)[0] == start  # not applied yet
    ph.action(port, sdk.BROADCAST_ID)
    assert ph.read4ByteTxRx(port, 13, 132)[0] == start - 200
    assert ph.reboot(port, 13) == (sdk.COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 13, 64)[0] == 0  # RAM back to defaults: torque off


def test_status_return_level_and_broadcast_ping(bus):
    world, emu, port, ph = bus
    # status return level 1: the device answers pings and reads only (the write setting it included)
    assert ph.write1ByteTxRx(port, 14, 68, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert ph.write1ByteTxRx(port, 14, 65, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert ph.read1ByteTxRx(port, 14, 65)[:2] == (1, sdk.COMM_SUCCESS)
    found, res = ph.broadcastPing(port)
    assert res == sdk.COMM_SUCCESS
    assert found == {11: [1020, 46], 12: [1020, 46], 13: [1020, 46], 14: [1020, 46], 200: [0x5A01, 1]}


def test_hardware_error_sets_alert_and_torque_off_until_reboot(bus):
    world, emu, port, ph = bus
    for i in IDS:
        ph.write1ByteTxRx(port, i, 64, 1)
    world.faults.inject("device_fault", device=12)
    _, res, err = ph.read1ByteTxRx(port, 12, 64)
    assert res == sdk.COMM_SUCCESS and err & 0x80  # alert bit
    assert ph.read1ByteTxRx(port, 12, 64)[0] == 0  # shutdown: torque off
    assert ph.read1ByteTxRx(port, 12, 70)[0] == 0x20  # overload
    assert ph.write1ByteTxRx(port, 12, 64, 1)[1] == 0x81  # refused until reboot (result fail + alert)
    assert emu.settled() and not world.enabled()[1]  # (its joint falls: no brake; the world takes its time)
    assert ph.reboot(port, 12)[0] == sdk.COMM_SUCCESS
    assert ph.read1ByteTxRx(port, 12, 70)[:3] == (0, sdk.COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 12, 64, 1) == (sdk.COMM_SUCCESS, 0)
    assert emu.settled() and world.enabled()[1]


def test_wire_timing_delays_answers_by_the_wire_time():
    world = World.default(model="omx")
    emu = DynamixelEmulator(world, ids=IDS, baud=57600, wire_timing=True, return_delay=250)
    port = DxlPort(emu.start().path, latency_ms=50)
    try:
        assert port.openPort() and port.setBaudRate(57600)
        ph = sdk.PacketHandler(2.0)
        g = sdk.GroupSyncRead(port, ph, 132, 4)
        for i in IDS:
            g.addParam(i)
        import time

        t0 = time.perf_counter()
        for _ in range(3):
            assert g.txRxPacket() == sdk.COMM_SUCCESS
        dt = (time.perf_counter() - t0) / 3
        # 18 B request + 4 x (500 us return delay + 15 B status) at 10 bits/byte, 57600 baud
        wire = (18 + 4 * 15) * 10 / 57600 + 4 * 500e-6
        assert wire <= dt < wire + 0.05
    finally:
        port.closePort()
        emu.stop()


def test_emulator_rejects_bad_configuration():
    world = World.default(model="omx")
    with pytest.raises(ValueError, match="one id per joint"):
        DynamixelEmulator(world, ids=[1, 2, 3])
    with pytest.raises(ValueError, match="collides"):
        DynamixelEmulator(world, ids=[1, 2, 3, 200])
    with pytest.raises(ValueError, match="baud"):
        DynamixelEmulator(world, ids=[1, 2, 3, 4], baud=12345)
    assert os.path.exists("/dev/ptmx")


def test_a_goal_written_while_a_fall_is_settled_is_the_one_the_servo_holds(bus):
    """Torque off and on again (as a homing-offset write does), then a new goal, all while the instant world
    still settles the fall on its worker (slow on a loaded host): the servo holds the goal it was given, not
    where the fall left the joint."""
    world, emu, port, ph = bus
    assert ph.write1ByteTxRx(port, 11, 64, 1)[0] == sdk.COMM_SUCCESS
    set_enabled = world.set_enabled
    slow = threading.Event()

    def slow_fall(on, joints=None):
        if not on:
            slow.set()
            time.sleep(0.5)  # the worker settling the fall, late
        return set_enabled(on, joints) if joints is not None else set_enabled(on)
    world.set_enabled = slow_fall
    present, res, _ = ph.read4ByteTxRx(port, 11, 132)
    assert res == sdk.COMM_SUCCESS
    assert ph.write1ByteTxRx(port, 11, 64, 0)[0] == sdk.COMM_SUCCESS
    assert slow.wait(2)
    assert ph.write1ByteTxRx(port, 11, 64, 1)[0] == sdk.COMM_SUCCESS
    goal = present + 150
    assert ph.write4ByteTxRx(port, 11, 116, goal)[0] == sdk.COMM_SUCCESS
    assert emu.settled(5)
    assert ph.read4ByteTxRx(port, 11, 116)[:2] == (goal, sdk.COMM_SUCCESS)
