"""The emulated drives' own clock: a real drive runs in real time, the emulator in threads of a process that a
loaded test machine may not schedule for a while. Time this process did not run at all is not time a drive
could have watched (a heartbeat consumer, say), so it counts only ``own_gap`` of each gap (the rule of
``station.robot.silence.Silence`` on the station side, which the mocks may not import)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class OwnClock:
    """``now()``: seconds the emulator could watch, its own scheduling gaps beyond ``own_gap`` not counted.
    ``tick()`` once per turn of a loop that turns at least every ``own_gap`` while anything is being timed."""

    def __init__(self, own_gap: float = 0.05, clock: Callable[[], float] = time.monotonic) -> None:
        self.own_gap = own_gap
        self._clock = clock
        self._lock = threading.Lock()
        self._last = clock()
        self._observed = 0.0

    def tick(self) -> float:
        with self._lock:
            t = self._clock()
            self._observed += min(t - self._last, self.own_gap)
            self._last = t
            return self._observed

    def now(self) -> float:
        with self._lock:
            return self._observed + min(self._clock() - self._last, self.own_gap)
