"""Dynamixel Protocol 2.0 bus emulator (pty) serving the simulated world; see docs/hardware-dynamixel.md.

Names are imported on first use (PEP 562), so registering `station mock dynamixel` costs no numpy."""

from __future__ import annotations

import importlib

_WHERE = {
    "DEFAULT_CONTACT_ID": "station.mocks.dynamixel.emulator",
    "DynamixelEmulator": "station.mocks.dynamixel.emulator",
    "CONTACT_SENSOR": "station.mocks.dynamixel.tables",
    "XL430_W250": "station.mocks.dynamixel.tables",
    "XM430_W350": "station.mocks.dynamixel.tables",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value
    return value
