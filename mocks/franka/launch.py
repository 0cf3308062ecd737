"""Start ``station mock franka`` as a child process and hand out the robot URL (tests, benchmarks, scripts)::

    with FrankaEmulator("world.yaml") as emu:
        robot = open_robot(emu.url)

The launcher's emulator for bus ``franka`` (``station.mocks.launch``): the child serves on a free random
loopback address (libfranka's port 1337 is fixed: one robot per address, so emulators of parallel test sessions
never meet), ends with its parent and is terminated on ``close()``."""

from __future__ import annotations

import os

from station.mocks.launch import Emulator


class FrankaEmulator(Emulator):
    def __init__(self, world: str | os.PathLike, *, host: str | None = None, serial: str | None = None,
                 extra: tuple[str, ...] = (), env: dict | None = None, timeout: float = 60.0) -> None:
        super().__init__("franka", world, host=host, serial=serial, extra=extra, env=env, timeout=timeout)
