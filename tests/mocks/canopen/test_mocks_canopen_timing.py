"""``station.mocks.canopen.timing``: the emulated drive's clock counts only ``own_gap`` of a stretch in which
its process was not scheduled (driven by a hand-set clock: the gaps are exact)."""

from __future__ import annotations

import pytest
from station.mocks.canopen.timing import OwnClock


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_a_scheduling_gap_counts_own_gap_only():
    mono, wall = Clock(), Clock()
    c = OwnClock(own_gap=0.05, clock=mono, wall=wall)
    for _ in range(10):  # a loop turning every 10 ms: all of it observed
        mono.t += 0.01
        wall.t += 0.01
        c.tick()
    assert c.now() == pytest.approx(0.10)
    mono.t += 2.0  # the process was not run for 2 s
    wall.t += 2.0
    assert c.now() == pytest.approx(0.15)  # an ongoing gap counts own_gap
    c.tick()
    assert c.now() == pytest.approx(0.15)
    mono.t += 0.01
    wall.t += 0.01
    c.tick()
    assert c.now() == pytest.approx(0.16)
    # a frame stamped on the wire 5 ms after the 5th tick: observed time then, however late it is read
    assert c.at(100.055) == pytest.approx(0.055)
    assert c.at(wall.t + 10) == pytest.approx(0.16)  # never beyond now
