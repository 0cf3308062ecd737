"""The CiA 402 drives' emulator as the station's tools see it (``station.emulators`` entry point ``canopen``):
launched in the caller's process on a python-can ``virtual`` channel of a unique name (the default), or as
``station mock canopen`` in a child process (``process=True``: the same drives behind a socketcand hub on a free
port, in an interpreter of their own, as real drives are not starved by the station's host)."""

from __future__ import annotations

import uuid

from station.mocks.plug import CHILD, IN_PROCESS, Demo, Plug


class CanopenPlug(Plug):
    bus = "canopen"
    cli = "station.mocks.canopen.cli"
    modes = (IN_PROCESS, CHILD)
    default_model = "arm6"
    demo = Demo(model="arm6")

    def build(self, world):
        from station.mocks.canopen.emulator import CanopenEmulator

        return CanopenEmulator(world, "virtual", f"emu{uuid.uuid4().hex[:10]}")

    def child_args(self, emu) -> list[str]:
        return ["--port", "0"]  # any free port: side-by-side emulators never meet

    def child_url(self, emu, lines: list[str]) -> str:
        # "socketcand HOST:PORT channel can0 url canopen+socketcand://..."
        return lines[-1].rsplit(" url ", 1)[-1].strip()


PLUG = CanopenPlug()
