"""Robot protocol, capability protocols, typed errors and the URL registry.

Cheap to import: no numpy, no kinematics, no bus library (drivers are imported when their URL is opened),
and the names below are loaded from their modules on first use, so ``import station.robot.errors`` costs
only that module. Drivers subclass ``station.robot.base.RobotBase`` and use ``station.robot.motion`` (those
load numpy)."""

from __future__ import annotations

import importlib

_EXPORTS = {
    "station.robot.errors": ("BusError", "ConfigError", "ConnectionLost", "DeviceFault", "IdentityMismatch",
                             "LimitError", "SafetyStop", "StationError"),
    "station.robot.protocol": ("Identity", "JointSnapshot", "JointState", "Robot", "RobotStatus", "adopt_serial"),
    "station.robot.capabilities": ("CalibrationExport", "CalibrationStore", "CartesianMotion", "Compliant",
                                   "ContactSensor", "FaultRecovery", "Reboot", "Reconnect", "UnlockProtectiveStop",
                                   "capabilities_of"),
    "station.robot.registry": ("open_robot", "schemes"),
    "station.robot.url": ("RobotURL", "parse_ids", "parse_url"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'station.robot' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
