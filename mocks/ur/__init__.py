"""Universal Robots e-Series controller emulator (RTDE 30004, dashboard 29999, script port 30003) backed by
the simulated world; the real ``ur_rtde`` client talks to it unchanged. Run it in its own process:
``station mock ur --host 127.0.0.2 [--world FILE]`` (ur_rtde's constructors hold the GIL).

Names are imported on first use, so registering `station mock ur` costs no numpy."""

from station.lazy import lazy_names

_WHERE = {"URController": "station.mocks.ur.controller", "URServer": "station.mocks.ur.server"}
__all__ = sorted(_WHERE)
__getattr__ = lazy_names(__name__, _WHERE)
