"""The CiA 402 drives' emulator as the station's tools see it (``station.emulators`` entry point ``canopen``):
launched in the caller's process on a python-can ``virtual`` channel of a unique name (``station mock canopen``,
the same drives behind a socketcand hub for other processes, is a command of its own: it prints a socketcand
address, not the launcher's ready line)."""

from __future__ import annotations

import uuid

from station.mocks.plug import Demo, Plug


class CanopenPlug(Plug):
    bus = "canopen"
    cli = "station.mocks.canopen.cli"
    default_model = "arm6"
    demo = Demo(model="arm6")

    def build(self, world):
        from station.mocks.canopen.emulator import CanopenEmulator

        return CanopenEmulator(world, "virtual", f"emu{uuid.uuid4().hex[:10]}")


PLUG = CanopenPlug()
