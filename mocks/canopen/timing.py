"""The emulated drives' own clock: a real drive runs in real time, the emulator in threads of a process that a
loaded test machine may not schedule for a while. Time this process did not run at all is not time a drive
could have watched (a heartbeat consumer, say), so it counts only ``own_gap`` of each gap (the rule of
``station.robot.silence.Silence`` on the station side, which the mocks may not import)."""

from __future__ import annotations

import bisect
import collections
import threading
import time
from collections.abc import Callable


class OwnClock:
    """``now()``: seconds the emulator could watch, its own scheduling gaps beyond ``own_gap`` not counted.
    ``tick()`` once per turn of a loop that turns at least every ``own_gap`` while anything is being timed;
    ``at(stamp)``: the same clock at a frame's wall-clock timestamp (when it was on the wire: a drive's controller
    takes it then, however late this process's receive thread gets to it)."""

    def __init__(self, own_gap: float = 0.05, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time) -> None:
        self.own_gap = own_gap
        self._clock, self._wall = clock, wall
        self._lock = threading.Lock()
        self._last = clock()
        self._observed = 0.0
        self._marks: collections.deque[tuple[float, float]] = collections.deque(maxlen=2000)  # (wall, observed)

    def tick(self) -> float:
        with self._lock:
            t = self._clock()
            self._observed += min(t - self._last, self.own_gap)
            self._last = t
            self._marks.append((self._wall(), self._observed))
            return self._observed

    def now(self) -> float:
        with self._lock:
            return self._observed + min(self._clock() - self._last, self.own_gap)

    def at(self, stamp: float) -> float:
        """Observed time at wall-clock ``stamp`` (at most now): the last tick before it plus what followed it,
        capped at ``own_gap``."""
        with self._lock:
            now = self._observed + min(self._clock() - self._last, self.own_gap)
            marks = self._marks
            if not marks or stamp >= marks[-1][0]:
                last_wall = marks[-1][0] if marks else stamp
                return min(now, (marks[-1][1] if marks else now) + min(max(0.0, stamp - last_wall), self.own_gap))
            k = bisect.bisect_right(marks, (stamp, float("inf"))) - 1
            if k < 0:
                return marks[0][1]
            wall, observed = marks[k]
            return min(now, observed + min(stamp - wall, self.own_gap))
