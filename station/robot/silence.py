"""How long a link has been silent, as far as this process could watch it.

A stall timeout compares "no new data since" with a threshold. Measured on the wall clock alone, the time this
process itself was not running (a loaded station PC, a virtual machine paused by its host) counts against the
link: the process wakes, its deadline has passed, the peer's next package is a few ms away, and a healthy link
is called stalled. ``Silence`` counts each turn of the watching loop in full only when the turn was short; a
longer gap (the watcher was not scheduled) counts ``own_gap`` at most. A link that is really gone is still
called so: the loop goes on turning, and ``threshold`` accumulates within the threshold plus the watcher's own
absences, which it could not have acted in anyway."""

from __future__ import annotations

import time
from collections.abc import Callable


class Silence:
    """``tick()`` once per turn of a watching loop; ``reset()`` when the link shows new data. ``tick()`` returns
    the silence in seconds, own scheduling gaps beyond ``own_gap`` not counted."""

    def __init__(self, own_gap: float = 0.05, clock: Callable[[], float] = time.monotonic) -> None:
        self.own_gap = own_gap
        self._clock = clock
        # over the whole watch (``reset`` keeps them): the longest turn of the loop and the time not counted
        self.max_gap = 0.0
        self.uncounted = 0.0
        self.reset()

    def reset(self) -> None:
        self._last = self._clock()
        self.seconds = 0.0

    def tick(self) -> float:
        now = self._clock()
        gap = now - self._last
        self.seconds += min(gap, self.own_gap)
        self.max_gap = max(self.max_gap, gap)
        self.uncounted += max(0.0, gap - self.own_gap)
        self._last = now
        return self.seconds

    def note(self) -> str:
        """What a fault message says about the host: its longest scheduling gap while watching, and how much
        time was not counted as the link's silence."""
        return (f"host scheduling gap: longest {self.max_gap * 1e3:.0f} ms, {self.uncounted * 1e3:.0f} ms not "
                "counted as silence")
