"""Fault latching: an error seen on a bus thread (heartbeat lost, bus-off, EMCY) is kept until the robot is
enabled again and raised by every call in between; the first one stops the robot."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from station.robot.errors import StationError

log = logging.getLogger("station.drivers.canopen")


class FaultLatch:
    def __init__(self) -> None:
        self.error: StationError | None = None  # the first fault since the last clear: what calls raise
        self.messages: list[str] = []  # every fault since the last clear (status())
        self.fatal = False  # a fault enable() cannot clear (drive rebooted, server gone): reopen the robot
        self.on_first: list[Callable[[], None]] = []  # run once per latched fault, on the thread that saw it
        self._lock = threading.Lock()

    def latch(self, err: StationError, fatal: bool = False) -> None:
        with self._lock:
            first = self.error is None
            if first:
                self.error = err
            self.messages.append(str(err))
            self.fatal = self.fatal or fatal
        if first:
            # not a warning: every later call raises it, and the CLI prints it once as its error line
            log.info("canopen: fault latched: %s", err)
            for action in self.on_first:
                action()

    def raise_if_latched(self) -> None:
        if self.error is not None:
            raise self.error

    def clear(self) -> None:
        with self._lock:
            self.error = None
            self.messages.clear()
