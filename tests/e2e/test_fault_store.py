"""CANopen write-back durability: home offsets written to 0x607C but killed before the 0x1010
store live only in volatile memory and are gone after a power cycle (the emulator keeps volatile and stored
values apart); ``persist_calibration()`` re-sends the store so they survive. Truth: the emulated drives'
object dictionaries after an emulated power cycle, read again over SDO by a fresh robot."""

from __future__ import annotations

import time
import uuid

from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

from station.robot import open_robot


def _cycle_and_read(emu, url) -> list[int]:
    emu.power_cycle()
    time.sleep(0.3)  # boot-up
    with open_robot(url) as fresh:
        return [int(fresh.bus.sdo_read(n, 0x607C)) for n in fresh.nodes]


def test_unstored_offsets_lost_at_power_cycle_and_kept_after_persist():
    chan = f"st-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=2, time_mode="realtime")
    emu = CanopenEmulator(world, channel=chan).start()
    url = f"canopen+virtual://{chan}?nodes=1-6&model=arm6"
    try:
        counts = [1000 * (k + 1) for k in range(6)]
        robot = open_robot(url)
        for n, c in zip(robot.nodes, counts, strict=True):  # the write phase, killed before the store
            robot.bus.sdo_write(n, 0x607C, c)
        robot.close()
        assert _cycle_and_read(emu, url) == [0] * 6  # volatile only: gone (what the first fault campaign saw)

        robot = open_robot(url)
        for n, c in zip(robot.nodes, counts, strict=True):
            robot.bus.sdo_write(n, 0x607C, c)
        assert robot.persist_calibration() == [1, 2, 3, 4, 5, 6]  # what resume re-sends
        robot.close()
        assert _cycle_and_read(emu, url) == counts
    finally:
        emu.stop()
