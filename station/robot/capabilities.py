"""What a robot can do beyond the core ``Robot`` protocol, as small protocols (the labgrid idea).

Callers ask ``isinstance(robot, CalibrationStore)`` instead of probing with ``getattr`` or catching
``NotImplementedError``; a driver fulfils a capability by having its methods (no registration). All methods
take and return SI units and raise the typed errors of ``station.robot.errors``.

A capability says what the driver can do; whether this particular cell wired it can still differ: a
``ContactSensor`` whose URL configured no contact input answers ``touch()`` with ``None``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from pathlib import Path

    import numpy as np


@runtime_checkable
class CalibrationStore(Protocol):
    """The device stores joint zero corrections itself (Dynamixel homing offset 20, CiA 402 home offset 0x607C).

    ``read_calibration()`` returns ``{"offset.jN": value_SI}``, the correction the device applies to the
    position it reports; ``write_calibration(values)`` stores new absolute values persistently and reads
    them back (raises ``DeviceFault`` on a mismatch); afterwards the device reports ``q_raw + value``."""

    def read_calibration(self) -> dict[str, float]: ...
    def write_calibration(self, values: dict[str, float]) -> None: ...


@runtime_checkable
class WritePose(Protocol):
    """A ``CalibrationStore`` that stores only with a joint's power off (DYNAMIXEL: Homing Offset is EEPROM, written
    with Torque Enable = 0, and the servo has no brake): ``write_pose(values)`` answers where the arm must stand for
    ``write_calibration(values)`` (joint positions, SI; it may measure where the arm stands now, so it is asked
    again after each move), or None when it may write where it stands. Write-back takes the arm there on a
    collision-checked path first."""

    def write_pose(self, values: dict[str, float] | None = None) -> np.ndarray | None: ...


@runtime_checkable
class CalibrationExport(Protocol):
    """The controller keeps its calibration internally and nothing the station speaks can change it (UR):
    ``export_calibration`` writes files for the integrator to install (e.g. ``calibration.conf``, URDF) and
    returns their paths; the robot is unchanged. Write-back asks for this first: a robot that is both
    (UR's ``write_calibration`` exports too) is never written to."""

    def export_calibration(self, result_or_values: Any, folder: str | Path | None = None) -> list[Path]: ...


@runtime_checkable
class ContactSensor(Protocol):
    """The cell's contact input (needle touched, tip seated in a socket): ``True``/``False``, ``None`` when
    this robot's URL configured no input."""

    def touch(self) -> bool | None: ...


@runtime_checkable
class Compliant(Protocol):
    """A yielding mode (low torque / freedrive) so a socket can seat the tip; off holds where the arm rests."""

    def set_compliant(self, on: bool) -> None: ...


@runtime_checkable
class CartesianMotion(Protocol):
    """The controller moves its own TCP in straight lines: ``tcp_pose()`` = (x, y, z m, rx, ry, rz rotation
    vector) in the base frame from the controller's model; ``move_linear(pose, speed m/s, wait)``."""

    def tcp_pose(self) -> np.ndarray: ...
    def move_linear(self, pose: Any, speed: float | None = None, wait: bool = True) -> None: ...


@runtime_checkable
class UnlockProtectiveStop(Protocol):
    """Release a protective stop once its cause is gone (UR: dashboard ``unlock protective stop``, refused for
    5 s after the stop; ``wait`` retries until ``timeout``), then make the robot ready for motion again."""

    def unlock_protective_stop(self, wait: bool = True, timeout: float = 8.0) -> str: ...


@runtime_checkable
class Reboot(Protocol):
    """Restart one joint's device (joint index or name) to clear a latched hardware error; ``enable()`` after."""

    def reboot(self, joint: int | str) -> None: ...


@runtime_checkable
class Reconnect(Protocol):
    """Reopen every channel after ``ConnectionLost`` (retrying until ``timeout`` s)."""

    def reconnect(self, timeout: float = 10.0) -> None: ...


@runtime_checkable
class VelocityJog(Protocol):
    """Non-blocking velocity jog for hold-to-run (UR: speedJ/speedL under the RTDE watchdog).

    ``jog_velocity(mode "joint"|"cartesian", axis, velocity rad/s or m/s, frame "base"|"tool")`` returns at
    once; the robot keeps that speed only while the caller re-sends within the driver's watchdog period (it
    stops by itself otherwise); ``stop()`` ends it. The tool never exceeds 0.25 m/s."""

    def jog_velocity(self, mode: str, axis: int, velocity: float, frame: str = "base") -> None: ...


# A fault enable() alone cannot clear: ``isinstance(robot, FaultRecovery)`` is true when the robot offers any
# of these recoveries; ask for the one you need by its own protocol.
FaultRecovery = (UnlockProtectiveStop, Reboot, Reconnect)


CAPABILITIES = (CalibrationStore, CalibrationExport, ContactSensor, Compliant, CartesianMotion, UnlockProtectiveStop,
                Reboot, Reconnect, VelocityJog, WritePose)


def capabilities_of(robot: object) -> list[str]:
    """Names of the capabilities ``robot`` fulfils (for ``station`` output and logs)."""
    return [c.__name__ for c in CAPABILITIES if isinstance(robot, c)]
