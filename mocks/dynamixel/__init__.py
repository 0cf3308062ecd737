"""Dynamixel Protocol 2.0 bus emulator (pty) serving the simulated world; see docs/hardware-dynamixel.md."""

from station.mocks.dynamixel.emulator import DEFAULT_CONTACT_ID, DynamixelEmulator
from station.mocks.dynamixel.tables import CONTACT_SENSOR, XL430_W250, XM430_W350

__all__ = ["CONTACT_SENSOR", "DEFAULT_CONTACT_ID", "DynamixelEmulator", "XL430_W250", "XM430_W350"]
