"""Dynamixel Protocol 2.0 bus emulator (pty) serving the simulated world; see docs/hardware-dynamixel.md.

Names are imported on first use, so registering `station mock dynamixel` costs no numpy."""

from station.lazy import lazy_names

_WHERE = {
    "DEFAULT_CONTACT_ID": "station.mocks.dynamixel.emulator",
    "DynamixelEmulator": "station.mocks.dynamixel.emulator",
    "CONTACT_SENSOR": "station.mocks.dynamixel.tables",
    "XL430_W250": "station.mocks.dynamixel.tables",
    "XM430_W350": "station.mocks.dynamixel.tables",
}
__all__ = sorted(_WHERE)
__getattr__ = lazy_names(__name__, _WHERE)
