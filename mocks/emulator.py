"""What every emulator shares (python-can's ``BusABC`` idea, on the far side of the wire): ``start()`` returns the
started emulator, ``stop()`` runs the emulator's own ``_shutdown()`` once per start (a second call does nothing),
``with emulator:`` starts and stops it, ``url`` is what the station (or an instrument client) opens, ``world``
the simulated world it serves, and ``power_cycle()`` switches the emulated device off and on: what the device
keeps on its non-volatile store survives, everything volatile is lost.

A subclass implements ``_startup()`` (may raise: whatever it opened is released again through ``_shutdown()``),
``_shutdown()`` (tolerates a half-started emulator), ``url`` and ``power_cycle()``. The launcher
(``station.mocks.launch``) and the ``station.emulators`` entry points (``station.mocks.plug``) start every bus's
emulator through this face."""

from __future__ import annotations

import threading
from typing import Any, Self


class EmulatorBase:
    world: Any = None  # the World this emulator serves; None when it runs in another process

    # no __init__: subclasses keep their own constructors; the lifecycle state is created on first use
    def _life(self) -> threading.Lock:
        lock = self.__dict__.get("_life_lock")
        if lock is None:
            lock = self.__dict__.setdefault("_life_lock", threading.Lock())
        return lock

    @property
    def started(self) -> bool:
        """Started and not stopped since."""
        return bool(self.__dict__.get("_live", False))

    def start(self) -> Self:
        """Start serving (a started emulator is returned as it is). On failure, what was opened is released."""
        with self._life():
            if self.started:
                return self
            try:
                self._startup()
            except BaseException:
                self._shutdown()
                raise
            self._live = True
        return self

    def stop(self) -> None:
        """Stop serving and release every resource; calling it again (or on an emulator never started) does
        nothing."""
        with self._life():
            if not self.started:
                return
            self._live = False
        self._shutdown()

    def close(self) -> None:
        """The same as :meth:`stop` (the name the station's own objects use)."""
        self.stop()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---- what a subclass provides ------------------------------------------------------------------------
    @property
    def url(self) -> str:
        """The URL a client opens for this emulator (a robot URL, or an instrument URL for the tracker)."""
        raise NotImplementedError

    def power_cycle(self) -> None:
        """Switch the emulated device off and on: the non-volatile store is kept, volatile state is lost."""
        raise NotImplementedError(f"{type(self).__name__} has no power cycle")

    def _startup(self) -> None:
        raise NotImplementedError

    def _shutdown(self) -> None:
        raise NotImplementedError
