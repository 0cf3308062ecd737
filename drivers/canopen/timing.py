"""Timeouts that count only what the station could have observed (issue: spurious faults on a busy PC).

A timeout compares "no answer since" with a limit. On the wall clock alone, time in which this process was not
scheduled (a loaded PC, a paused virtual machine) counts against the drive: the station wakes, its deadline has
passed, the answer is in the socket's buffer. ``Deadline`` counts each turn of a waiting loop in full only when
the turn was short (``station.robot.silence.Silence``); ``HostWatch`` keeps the scheduling gaps the watchdog
thread saw, for waits that block inside a library (python-canopen's SDO client) and cannot tick. A drive that
is really silent is still found: the loop turns on, and the limit accumulates within the limit plus the gaps
the station could not have acted in anyway. Each fault message names the timeout and the host's gaps."""

from __future__ import annotations

import collections
import threading
import time

from station.robot.silence import Silence


class Deadline:
    """``expired()`` once per turn of a waiting loop: True when ``seconds`` of observed time have passed."""

    def __init__(self, seconds: float, own_gap: float) -> None:
        self.seconds = seconds
        self.silence = Silence(own_gap=own_gap)

    def expired(self) -> bool:
        return self.silence.tick() > self.seconds

    def note(self) -> str:
        return self.silence.note()


class HostWatch:
    """The station's own scheduling gaps, as one regularly turning thread (the heartbeat watchdog) saw them:
    ``turn()`` once per turn; ``stalled(t0, t1)`` = seconds of [t0, t1] (monotonic) this process was not
    running beyond ``own_gap`` per gap, an ongoing gap (no turn for longer than ``own_gap``) included."""

    def __init__(self, own_gap: float) -> None:
        self.own_gap = own_gap
        self._lock = threading.Lock()
        self._last = time.monotonic()
        self._gaps: collections.deque[tuple[float, float]] = collections.deque(maxlen=256)
        self.max_gap = 0.0

    def turn(self) -> None:
        now = time.monotonic()
        with self._lock:
            gap = now - self._last
            self.max_gap = max(self.max_gap, gap)
            if gap > self.own_gap:
                self._gaps.append((self._last + self.own_gap, now))
            self._last = now

    def stalled(self, t0: float, t1: float) -> float:
        with self._lock:
            gaps = list(self._gaps)
            if time.monotonic() - self._last > self.own_gap:
                gaps.append((self._last + self.own_gap, time.monotonic()))
        return sum(max(0.0, min(b, t1) - max(a, t0)) for a, b in gaps)

    def note(self, t0: float, t1: float) -> str:
        return (f"host scheduling gap: {self.stalled(t0, t1) * 1e3:.0f} ms of the wait not run, longest seen "
                f"{self.max_gap * 1e3:.0f} ms")
