"""The Dynamixel bus emulator as the station's tools see it (``station.emulators`` entry point ``dynamixel``):
in the caller's process on a pty, or as ``station mock dynamixel`` in a child process (``process=True``: a
realtime demo keeps the emulator's timing out of the station's GIL). Either reads the world's
``buses.dynamixel`` section (ids, servo, baud, firmware, ...)."""

from __future__ import annotations

from station.mocks.plug import CHILD, IN_PROCESS, Demo, Plug


class DynamixelPlug(Plug):
    bus = "dynamixel"
    cli = "station.mocks.dynamixel.cli"
    modes = (IN_PROCESS, CHILD)
    ready_lines = 2  # the pty path, then "robot URL dynamixel://PATH?..."
    default_model = "omx"
    # one socket on a 4-axis arm cannot separate the first two zeros from the socket's position: the surveyed
    # cell position is used instead (docs/procedures.md)
    demo = Demo(model="omx", options={"reference": "cell", "cone_deg": 70.0})

    def build(self, world):
        from station.mocks.dynamixel.cli import emulator_for

        return emulator_for(world)

    def child_args(self, emu) -> list[str]:
        return ["--serial", emu.serial] if emu.serial else []

    def serial_in_url(self, emu) -> bool:
        return emu.emulator is not None  # in-process: the launcher adds it; a child prints its own

    def child_url(self, emu, lines: list[str]) -> str:
        emu.port = lines[0]
        return super().child_url(emu, lines)


PLUG = DynamixelPlug()
