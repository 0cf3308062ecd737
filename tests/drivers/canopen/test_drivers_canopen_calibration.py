"""``station.drivers.canopen.calibration``: the zero a CiA 402 drive applies (``0x6064 - 0x6063``) read over the
wire by the driver against the emulated drive's own registers (``station.mocks.canopen.drive``), before and after
the driver sets a new zero by homing on the current position."""

from __future__ import annotations

from station.drivers.canopen.calibration import read_zero
from station.mocks.canopen.drive import Drive402
from station.mocks.world import World

START = [0.1, -0.5, 0.5, 0.2, 0.6, -0.3]


def test_the_zero_read_is_the_drives_and_moves_by_the_written_counts(robot_rig):
    world = World.default(model="arm6", seed=5, start=START, time_mode="instant")
    emu, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
    drives: dict[int, Drive402] = emu.drives
    before = {n: read_zero(robot.bus, n) for n in robot.nodes}
    for n, z in before.items():
        d = drives[n]
        assert (z.position, z.internal) == (d.position_actual(), d.internal_value())  # the drive's registers
        assert z.offset == d.position_actual() - d.internal_value()
    cal = robot.read_calibration()
    robot.write_calibration({**cal, "offset.j2": cal["offset.j2"] + 0.002})
    after = {n: read_zero(robot.bus, n) for n in robot.nodes}
    d2 = drives[robot.nodes[1]]
    counts = d2.counts_of(0.002) - d2.counts_of(0.0)  # 2 mrad in this drive's increments
    assert abs((after[robot.nodes[1]].offset - before[robot.nodes[1]].offset) - counts) <= 1
    assert after[robot.nodes[1]].internal == before[robot.nodes[1]].internal  # the arm did not move
    assert all(after[n].offset == before[n].offset for n in robot.nodes if n != robot.nodes[1])
