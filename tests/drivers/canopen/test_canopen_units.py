"""Drive units (CiA 402 0x60A8/0x60A9, factor group 0x608F-0x6092) as vendors set them by default, and the
driver reading them before any motion: a drive in rpm gets rpm (Synapticon 0x60A9 default 0x00B44700, Nanotec
PD6-C 60A9h preset 00B44700h), a drive counting another position resolution is refused in one line. Truth: the
world's joint motion and the frames on the wire."""

from __future__ import annotations

import time
import uuid

import can
import numpy as np
import pytest
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

from station.robot import IdentityMismatch, open_robot

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(0)) is not None:
        out.append(m)
    return out


@pytest.mark.parametrize("unit, per_rpm", [("rpm", 1.0), ("0.001rpm", 1000.0)])
def test_a_drive_in_rpm_gets_rpm_and_moves_at_the_commanded_speed(unit, per_rpm):
    """A drive whose velocity unit is motor rpm: counts/s sent as they are would ask for thousands of rpm (the
    joint at its maximum speed); the driver converts. Checked on the wire (the profile velocity in RPDO2 equals
    the joint speed in motor rpm) and in the world (the move lasts as long as the commanded speed says)."""
    chan = f"u-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=7, start=START, time_mode="realtime",
                          buses={"canopen": {"velocity_unit": unit}})
    with CanopenEmulator(world, channel=chan) as emu, open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6") \
            as robot:
        robot.enable()
        sniff = can.Bus(interface="virtual", channel=chan)
        try:
            q0 = robot.joint_positions().q
            target = q0.copy()
            target[1] += 0.15  # joint 2 alone: 0.15 rad at 0.3 rad/s, about 0.5 s
            drain(sniff)
            t0 = time.monotonic()
            robot.move_joints(target, speed=0.3)
            took = time.monotonic() - t0
            rpdo2 = [m for m in drain(sniff) if m.arbitration_id == 0x302]
        finally:
            sniff.shutdown()
        assert np.max(np.abs(world.encoder_q() - target)) < 1e-5
        enc = world.nominal.joints[1].encoder
        motor_rpm = 0.3 * abs(enc.gear) / (2 * np.pi) * 60  # 0.3 rad/s at the joint
        sent = int.from_bytes(bytes(rpdo2[0].data[1:5]), "little")
        assert sent == pytest.approx(motor_rpm * per_rpm, rel=0.01, abs=1)
        assert emu.drives[2].get(0x60A9) & 0xFFFFFF == 0xB44700
        assert took > 0.45, took  # counts/s taken as rpm would have run the joint at its maximum speed


def test_a_drive_counting_16_bit_positions_is_refused_before_motion():
    """A drive that counts 2^16 increments per motor revolution (its position unit) while the model says the
    arm's encoder: the joint would move by the wrong angle. One line naming both, no RPDO sent."""
    chan = f"u-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=7, start=START, buses={"canopen": {"position_resolution": 65536}})
    with CanopenEmulator(world, channel=chan) as emu:
        assert emu.drives[1].internal_value() != round(float(world.nominal.joints[0].encoder.to_counts(
            world.encoder_q()[0])))  # the drive really reports in its own resolution
        sniff = can.Bus(interface="virtual", channel=chan)
        try:
            with pytest.raises(IdentityMismatch, match=r"node 1 .*65536 counts/motor rev.*nothing was moved") as e:
                open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6")
            assert "\n" not in str(e.value)
            assert not [m for m in drain(sniff) if m.arbitration_id in {*range(0x201, 0x207), *range(0x301, 0x307)}]
        finally:
            sniff.shutdown()


def test_world_file_vendor_keys_are_checked():
    for bad, what in (({"velocity_unit": "furlong"}, "velocity_unit"), ({"incremental": [9]}, "incremental"),
                      ({"home_offset": "sideways"}, "home_offset"), ({"bogus": 1}, "unknown key")):
        world = World.default(model="arm6", buses={"canopen": bad})
        with pytest.raises(ValueError, match=what):
            CanopenEmulator(world, channel="x")
