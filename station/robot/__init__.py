"""Robot protocol, capability protocols, typed errors and the URL registry.

Cheap to import: no numpy, no kinematics, no bus library (drivers are imported when their URL is opened),
and the names below are loaded from their modules on first use, so ``import station.robot.errors`` costs
only that module. Drivers subclass ``station.robot.base.RobotBase`` and use ``station.robot.motion`` (those
load numpy)."""

from __future__ import annotations

from station.lazy import lazy_exports

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
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
