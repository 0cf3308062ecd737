"""``station.drivers.canopen.faults``: the first fault is kept and raised by every call until cleared."""

from __future__ import annotations

import threading

import pytest
from station.drivers.canopen.faults import FaultLatch

from station.robot.errors import StationError


def test_the_first_fault_is_raised_until_cleared():
    latch = FaultLatch()
    stops = []
    latch.on_first.append(lambda: stops.append(threading.current_thread().name))
    latch.raise_if_latched()  # nothing yet
    first, second = StationError("heartbeat of node 3 lost"), StationError("bus-off")
    t = threading.Thread(target=latch.latch, args=(first,), name="bus")
    t.start()
    t.join()
    latch.latch(second, fatal=True)
    assert stops == ["bus"]  # the stop ran once, on the thread that saw the fault
    for _ in range(2):
        with pytest.raises(StationError) as e:
            latch.raise_if_latched()
        assert e.value is first
    assert latch.messages == ["heartbeat of node 3 lost", "bus-off"] and latch.fatal
    latch.clear()
    latch.raise_if_latched()
    assert latch.messages == []
