"""Errors of the far side of the wire. The mocks import nothing from the station side (``station.robot``,
drivers, engine): like a real controller, they share no code with the client that talks to them."""


class MockError(Exception):
    """Bad emulator or world input (world file, id list, EEPROM file, listen address). The ``station mock``
    commands print it as one line ``station: error: ...`` and exit 2."""
