"""The UR controller emulator as the station's tools see it (``station.emulators`` entry point ``ur``): always
``station mock ur`` in a child process (ur_rtde's constructors hold the GIL, so the controller must not be a
thread of the process that uses ur_rtde), on a random free loopback address 127.x.y.z of its own (ur_rtde's ports
are fixed; random, so test sessions running side by side do not pick the same one)."""

from __future__ import annotations

import time

from station.mocks.errors import MockError
from station.mocks.plug import CHILD, Demo, Plug


class URPlug(Plug):
    bus = "ur"
    cli = "station.mocks.ur.cli"
    modes = (CHILD,)
    default_model = "ur5e"
    demo = Demo(model="ur5e")

    def child_args(self, emu) -> list[str]:
        from station.mocks.launch import free_loopback

        emu.host = emu.host or free_loopback()
        return ["--host", emu.host, *(["--serial", emu.serial] if emu.serial else [])]

    def serial_in_url(self, emu) -> bool:
        return False  # the controller reports its serial number (dashboard `get serial number`)

    def power_cycle_child(self, emu, boot_timeout: float = 30.0) -> None:
        """The controller reboots (``emulator power_cycle`` on its dashboard): every connection drops, the ports
        refuse while it boots, it comes back with the arm powered off. Returns once the dashboard answers again."""
        reply = emu.dashboard("emulator power_cycle")
        if "power cycle" not in reply:
            raise MockError(f"ur emulator: power cycle refused: {reply}")
        deadline = time.monotonic() + boot_timeout
        down = False
        while True:  # the ports close as the reboot starts (just after the reply), then listen again
            try:
                answered = emu.dashboard("robotmode", timeout=1.0).startswith("Robotmode:")
            except OSError:
                answered, down = False, True
            if answered and down:
                return
            if time.monotonic() > deadline:
                raise MockError(f"ur emulator on {emu.host}: not back within {boot_timeout:.0f} s of a power cycle")
            time.sleep(0.05)

PLUG = URPlug()
