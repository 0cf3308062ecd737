"""Bringing the tool tip onto a reference point: one protocol, fulfilled automatically (compliant seating in a
socket, guarded approach on the contact input) or by a technician jogging until the touch indicator lights
(labgrid's ManualPowerDriver idea: the same step, a person does the physical part)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from station.robot.capabilities import Compliant, ContactSensor
from station.robot.errors import ConfigError, DeviceFault

if TYPE_CHECKING:
    from station.engine.plan import PlannedPose, PosePlan


class Session(Protocol):
    """What a touch needs of the session it works for (``station.engine.session.Session`` is one): the robot, the
    model and plan it moves by, where it aims and how fast it goes near a point, and the operator. Named here so
    that the session imports the touches and not the other way round."""

    robot: Any
    model: Any
    current_plan: PosePlan | None

    def aimed_q(self, pose: PlannedPose) -> np.ndarray: ...
    def touch_speed(self, q_from, q_to) -> float: ...
    def point(self, label: str) -> Any: ...
    def ask(self, question, kind: str = "confirm", **spec) -> str | float: ...


class TouchFailed(DeviceFault):
    """The tip could not be brought onto the reference (socket not captured, no contact)."""


class TouchProvider(Protocol):
    """``bring_to`` ends with the tip on the reference (touch lit where the robot has an indicator);
    ``release`` leaves it (back to the approach pose)."""

    def bring_to(self, s: Session, pose: PlannedPose) -> None: ...
    def release(self, s: Session, pose: PlannedPose) -> None: ...


def _indicator(robot) -> bool | None:
    """The touch indicator; ``None`` for a robot without one."""
    return robot.touch() if isinstance(robot, ContactSensor) else None


def _wait(cond, timeout: float, poll: float = 0.005) -> bool:
    end = time.monotonic() + timeout
    while True:
        if cond():
            return True
        if time.monotonic() >= end:
            return False
        time.sleep(poll)


def along_approach(s: Session, pose: PlannedPose, q_ref: np.ndarray, depth: float, seed: np.ndarray) -> np.ndarray:
    """Joint target with the tip ``depth`` metres past where ``q_ref`` puts it along the point's approach axis
    (towards the point; negative: back out), same orientation."""
    model = s.model
    T = model.fk(q_ref)
    T[:3, 3] -= s.point(pose.point).approach * depth
    full = model.n_joints >= 6
    r = model.ik(T if full else T[:3, 3], seed, position_only=not full)
    if not r.ok[0]:
        where = f"{depth * 1e3:.2f} mm down" if depth >= 0 else f"{-depth * 1e3:.2f} mm short of the seated pose"
        raise TouchFailed(f"pose {pose.index}: the approach towards {pose.point} leaves the reachable space {where}")
    return r.q[0]


class SocketSeating:
    """Automatic: move to the nominal touch pose (the tip lands within the socket's capture radius), switch to
    compliant mode and let the ball seat in the cone; the joints are read while still compliant.

    The aim is corrected as the session goes: the nominal position of the seated tip at earlier poses tells
    where the station's model puts the socket, which keeps later poses well inside the capture radius."""

    def __init__(self, settle_timeout: float = 5.0, search_radius: float | None = None) -> None:
        self.settle_timeout = settle_timeout
        self.search_radius = search_radius

    def bring_to(self, s: Session, pose: PlannedPose) -> None:
        robot = s.robot
        if not isinstance(robot, Compliant):
            raise ConfigError(f"socket {pose.point}: seating needs a compliant mode, which this robot does not have")
        target = s.aimed_q(pose)
        standoff = float(getattr(robot, "seat_standoff", 0.0) or 0.0)
        if standoff > 0:  # a robot that presses: stiff to short of the cone, the press seats the ball
            target = along_approach(s, pose, target, -standoff, target)
        robot.move_joints(target, speed=s.touch_speed(pose.approach_arr, target))
        robot.set_compliant(True)
        # the touch indicator lights once the ball sits in the cone; a robot without one (touch() is None) is
        # trusted to have seated once it rests
        state = {"touch": None}

        def lit() -> bool:
            state["touch"] = _indicator(robot)
            return state["touch"] is not False

        if _wait(lit, self.settle_timeout) and (state["touch"] or _wait(
                lambda: not robot.status().moving, self.settle_timeout)):
            return
        robot.set_compliant(False)
        raise TouchFailed(f"pose {pose.index}: the tip did not seat in socket {pose.point} within "
                          f"{self.settle_timeout:g} s (outside the capture radius? check the cell file)")

    def release(self, s: Session, pose: PlannedPose) -> None:
        s.robot.set_compliant(False)
        s.robot.move_joints(pose.approach_arr)


class GuardedApproach:
    """Automatic, for a needle on the contact input: from the approach pose, step along the approach axis until
    the contact closes, then bisect the last step until the contact point is known to ``fine``."""

    def __init__(self, coarse: float = 1.0e-3, fine: float = 0.01e-3, travel: float = 0.05,
                 standoff: float = 5e-3) -> None:
        self.coarse, self.fine, self.travel, self.standoff = coarse, fine, travel, standoff

    def _at(self, s: Session, pose: PlannedPose, depth: float, seed: np.ndarray) -> np.ndarray:
        """Joint target ``depth`` metres past the approach pose along the approach axis (same orientation)."""
        return along_approach(s, pose, pose.approach_arr, depth, seed)

    def bring_to(self, s: Session, pose: PlannedPose) -> None:
        robot = s.robot
        if not isinstance(robot, ContactSensor):
            raise ConfigError(f"needle {pose.point}: a guarded approach needs a contact input, which this robot "
                              "does not have")
        q = pose.approach_arr
        # straight to a standoff above where the model puts the point, then in steps
        clearance = float((s.current_plan.settings if s.current_plan else {}).get("clearance_m", 0.03))
        depth = max(0.0, clearance - self.standoff)
        if depth > 0:
            q_next = self._at(s, pose, depth, q)
            robot.move_joints(q_next, speed=s.touch_speed(q, q_next))
            q = q_next
            if robot.touch():
                raise TouchFailed(f"pose {pose.index}: contact with {pose.point} already {self.standoff * 1e3:g} mm "
                                  "before the nominal point; check the cell file")
        lo, hi = depth, None
        while depth < self.travel:
            depth = min(depth + self.coarse, self.travel)
            q_next = self._at(s, pose, depth, q)
            robot.move_joints(q_next, speed=s.touch_speed(q, q_next))
            q = q_next
            if robot.touch():
                hi = depth
                break
            lo = depth
        if hi is None:
            raise TouchFailed(f"pose {pose.index}: no contact with {pose.point} within {self.travel * 1e3:g} mm "
                              "of travel")
        while hi - lo > self.fine:  # contact closes somewhere in (lo, hi]: halve it
            mid = (lo + hi) / 2
            q_mid = self._at(s, pose, mid, q)
            robot.move_joints(q_mid, speed=s.touch_speed(q, q_mid))
            q = q_mid
            if robot.touch():
                hi = mid
            else:
                lo = mid
        if not robot.touch():
            q_hi = self._at(s, pose, hi, q)
            robot.move_joints(q_hi, speed=s.touch_speed(q, q_hi))
            if not robot.touch():
                raise TouchFailed(f"pose {pose.index}: contact with {pose.point} lost on the fine approach")

    def release(self, s: Session, pose: PlannedPose) -> None:
        s.robot.move_joints(pose.approach_arr)


class ManualTouch:
    """A technician jogs the tip onto the point (``station jog`` or the teach pendant) until the touch indicator
    lights, then confirms. The confirmations go through the session's one prompt API (``s.ask``: the terminal,
    or the operator panel, which shows the point's picture or a sketch of where it is); ``prompt(question)``
    overrides it (a ``Question`` is its text, so a callable taking plain text works)."""

    def __init__(self, prompt=None, require_indicator: bool = True, timeout: float = 600.0) -> None:
        self.prompt = prompt
        self.require_indicator = require_indicator
        self.timeout = timeout

    def _confirm(self, s: Session, text: str, point: str) -> None:
        from station.engine.procedure import Question

        q = Question(text, point=point)
        if self.prompt is not None:
            self.prompt(q)
        else:
            s.ask(q)

    def bring_to(self, s: Session, pose: PlannedPose) -> None:
        s.robot.move_joints(pose.approach_arr)
        self._confirm(s, f"Pose {pose.index + 1}/{len(s.current_plan or [])}: jog the tool tip onto point "
                         f"{pose.point} until the touch indicator lights, then confirm", pose.point)
        if self.require_indicator and _indicator(s.robot) is False and not _wait(
                lambda: bool(_indicator(s.robot)), self.timeout):
            raise TouchFailed(f"pose {pose.index}: the touch indicator did not light")

    def release(self, s: Session, pose: PlannedPose) -> None:
        if isinstance(s.robot, Compliant):
            s.robot.set_compliant(False)
        self._confirm(s, f"Jog the tool clear of point {pose.point}, then confirm", pose.point)


def provider_for(kind: str, name: str | None = None) -> TouchProvider:
    """Default provider for a reference kind (``socket``/``needle``) or by name (``manual``)."""
    name = name or ("seat" if kind == "socket" else "guarded")
    if name == "seat":
        return SocketSeating()
    if name == "guarded":
        return GuardedApproach()
    if name == "manual":
        return ManualTouch()
    from station.robot.errors import ConfigError

    raise ConfigError(f"touch method {name!r} is not one of seat, guarded, manual")
