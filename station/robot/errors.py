"""Typed errors. Each carries what a person needs to act; the CLI prints ``str(err)`` as one line."""

from __future__ import annotations


class StationError(Exception):
    """Base of every error the station raises on purpose (the CLI maps it to exit 2)."""


class ConfigError(StationError):
    """Bad URL, model file, limits file or other user input."""


class BusError(StationError):
    """The bus did not carry the message: timeout, corrupt frame, bus-off, port gone."""


class ConnectionLost(BusError):
    """The robot stopped answering (heartbeat lost, socket closed)."""


class DeviceFault(StationError):
    """A device reports a fault (servo hardware error, drive EMCY, controller fault)."""

    def __init__(self, message: str, *, device: str | None = None, code: int | None = None) -> None:
        super().__init__(message)
        self.device = device
        self.code = code


class SafetyStop(StationError):
    """Protective stop, safeguard stop or emergency stop: motion is halted by the robot."""


class LimitError(StationError):
    """A command would leave joint limits or exceed a speed cap; nothing was sent."""


class SerialMismatch(ConfigError):
    """The robot reports (or its URL configures) another serial than the one given for the unit: the wrong unit
    is in the cell, or the wrong label was scanned. Raised at connect, before anything is journaled."""

    def __init__(self, message: str, *, given: str | None = None, reported: str | None = None) -> None:
        super().__init__(message)
        self.given = given
        self.reported = reported


class IdentityMismatch(ConfigError):
    """The robot/devices on the bus are not what the URL's model (or its default) says: wrong UR type or
    series, wrong Dynamixel servo model, not a CiA 402 drive or a different product. Raised at connect,
    before any motion (exit 2)."""
