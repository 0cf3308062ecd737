"""``station.drivers.canopen.bus``: the driver's CANopen link (python-canopen over a python-can virtual bus) against
the emulated drives' object dictionaries: SDO reads, optional objects, every node at once with the first error in
node order, and the SYNC rounds' positions."""

from __future__ import annotations

import pytest
from station.drivers.canopen.bus import CanopenBus
from station.mocks.world import World

from station.robot.errors import DeviceFault

START = [0.1, -0.5, 0.5, 0.2, 0.6, -0.3]


def test_sdo_and_sync_rounds_against_the_drives(robot_rig):
    world = World.default(model="arm6", seed=5, start=START, time_mode="instant")
    emu, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
    bus: CanopenBus = robot.bus
    assert isinstance(bus, CanopenBus)
    for n in robot.nodes:
        d = emu.drives[n]
        assert bus.read_obj(n, 0x1018, 4, "u32") == d.get(0x1018, 4)  # serial number, CiA 301 identity
        assert bus.read_obj(n, 0x6063, 0, "i32") == d.internal_value()
    assert bus.read_opt(robot.nodes[0], 0x5FFF, 0, "u32") is None  # no such object: optional
    with pytest.raises(DeviceFault):
        bus.read_obj(robot.nodes[0], 0x5FFF, 0, "u32")
    assert bus.per_node(robot.nodes, lambda n: n * 10) == {n: n * 10 for n in robot.nodes}

    def third_fails(n):
        if n >= robot.nodes[2]:
            raise DeviceFault(f"node {n}")
        return n

    with pytest.raises(DeviceFault, match=f"node {robot.nodes[2]}$"):  # the first in node order
        bus.per_node(robot.nodes, third_fails)
    r = bus.round()
    latest = bus.latest()
    for n in robot.nodes:  # TPDO1 carries the position the drive reports
        assert latest[n][2] == emu.drives[n].position_actual()
    assert r is not None
