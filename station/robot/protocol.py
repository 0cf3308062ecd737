"""The one interface every bus adapter fulfils and the procedure engine uses (SI units throughout).

What only some robots can do (calibration store or export, contact input, compliance, Cartesian motion,
fault recovery) is a capability protocol in ``station.robot.capabilities``. numpy and the kinematics are
named for type checkers only: importing this module stays cheap."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np

    from station.kinematics import Model


@dataclass(frozen=True)
class JointSnapshot:
    """All joints read in one transaction. ``q`` in rad (revolute) / m (prismatic)."""

    q: np.ndarray
    raw: tuple[float | int, ...]  # device units as read (ticks, counts, rad)
    raw_unit: str  # e.g. "tick", "count", "rad"
    t: float  # host wall clock (time.time()) when the reply arrived
    t_device: float | None = None  # device/controller timestamp if the bus has one (s)


@dataclass(frozen=True)
class JointState:
    name: str
    enabled: bool
    moving: bool
    fault: str | None = None


@dataclass(frozen=True)
class RobotStatus:
    enabled: bool
    moving: bool
    faults: tuple[str, ...] = ()
    estop: bool = False
    protective_stop: bool = False
    compliant: bool = False
    joints: tuple[JointState, ...] = ()

    @property
    def ok(self) -> bool:
        return not (self.faults or self.estop or self.protective_stop)


@dataclass(frozen=True)
class Identity:
    vendor: str
    model: str  # kinematic model name, e.g. "ur5e"
    serial: str
    firmware: str = ""
    devices: tuple[dict, ...] = field(default_factory=tuple)  # per-joint/device ids, serials, firmware
    url: str = ""
    # where ``serial`` comes from: "robot" (the controller reports it), "url" (configured ``?serial=``),
    # "derived" (made from device ids: no robot serial exists on the bus), "operator" (adopted, see below)
    serial_source: str = "robot"


def adopt_serial(ident: Identity, serial: str | None) -> Identity:
    """The identity a session files under ``serial``. A serial the robot reports or the URL configures must
    match (else it is the wrong robot); one the driver derived from device ids is no robot serial, so the
    operator's replaces it (the device ids stay in ``devices``)."""
    from dataclasses import replace

    from station.robot.errors import SerialMismatch

    if not serial:
        return ident
    if ident.serial_source == "derived" or not ident.serial:
        return replace(ident, serial=str(serial), serial_source="operator")
    if ident.serial != str(serial):
        raise SerialMismatch(f"the robot reports serial {ident.serial!r}, not {serial!r} (wrong robot? "
                             f"serial from the {'URL' if ident.serial_source == 'url' else 'controller'})",
                             given=str(serial), reported=ident.serial)
    return ident


JogMode = Literal["joint", "cartesian"]


@runtime_checkable
class Robot(Protocol):
    """What every robot can do; every driver fulfils it. Methods raise typed errors from ``station.robot.errors``.

    A raised fault always leaves the robot stopped. For joint motion ``speed`` is the speed of the joint
    that moves most, per joint in its own unit (rad/s, m/s for a prismatic joint), every joint capped at
    its own maximum; for Cartesian motion it is the tool speed in m/s (jogs never above 0.25 m/s).
    ``close()`` leaves the bus in its safe state and releases it; calling it again does nothing.
    Anything more is a capability (``station.robot.capabilities``): ask with ``isinstance``.
    """

    model: Model  # nominal kinematic model the driver converts with

    def identity(self) -> Identity: ...
    def joint_positions(self) -> JointSnapshot: ...
    def move_joints(self, q: np.ndarray, speed: float | None = None, wait: bool = True) -> None: ...
    def jog(self, mode: JogMode, axis: int, step: float, speed: float | None = None) -> None: ...
    def stop(self) -> None: ...
    def enable(self) -> None: ...
    def disable(self) -> None: ...
    def status(self) -> RobotStatus: ...
    def close(self) -> None: ...
