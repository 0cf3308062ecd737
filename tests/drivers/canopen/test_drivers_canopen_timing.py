"""``station.drivers.canopen.timing``: the station's timeouts count only time it could have observed; the gaps
of a stalled host are kept by the watchdog's turns (time.monotonic set by hand: the gaps are exact)."""

from __future__ import annotations

import pytest
import station.drivers.canopen.timing as timing
from station.drivers.canopen.timing import HostWatch


def test_host_watch_keeps_the_gaps_beyond_own_gap(monkeypatch):
    now = [50.0]
    monkeypatch.setattr(timing.time, "monotonic", lambda: now[0])
    w = HostWatch(own_gap=0.1)
    for _ in range(5):
        now[0] += 0.05
        w.turn()
    now[0] += 1.0  # the watchdog thread was not scheduled for a second
    w.turn()
    assert w.max_gap == pytest.approx(1.0)
    t0 = 50.0
    assert w.stalled(t0, now[0]) == pytest.approx(0.9)  # the gap beyond own_gap
    assert w.stalled(t0, 50.3) == pytest.approx(0.0)  # a window before the gap
    assert w.stalled(50.6, 50.8) == pytest.approx(0.2)  # inside it
    now[0] += 0.5  # an ongoing gap counts too
    assert w.stalled(t0, now[0]) == pytest.approx(0.9 + 0.4)
    assert w.note(t0, now[0]) == "host scheduling gap: 1300 ms of the wait not run, longest seen 1000 ms"
