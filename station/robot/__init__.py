"""Robot protocol, typed errors and the URL registry (no bus library imported here)."""

from station.robot.errors import (
    BusError,
    ConfigError,
    ConnectionLost,
    DeviceFault,
    LimitError,
    SafetyStop,
    StationError,
)
from station.robot.protocol import Identity, JointSnapshot, JointState, Robot, RobotStatus, adopt_serial
from station.robot.registry import BACKENDS, RobotURL, open_robot, parse_ids, parse_url

__all__ = [
    "BACKENDS", "BusError", "ConfigError", "ConnectionLost", "DeviceFault", "Identity", "JointSnapshot",
    "JointState", "LimitError", "Robot", "RobotStatus", "RobotURL", "SafetyStop", "StationError",
    "adopt_serial", "open_robot", "parse_ids", "parse_url",
]
