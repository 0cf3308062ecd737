"""Universal Robots e-Series controller emulator (RTDE 30004, dashboard 29999, script port 30003) backed by
the simulated world; the real ``ur_rtde`` client talks to it unchanged. Run it in its own process:
``station mock ur --host 127.0.0.2 [--world FILE]`` (ur_rtde's constructors hold the GIL)."""

from station.mocks.ur.controller import URController
from station.mocks.ur.server import URServer

__all__ = ["URController", "URServer"]
