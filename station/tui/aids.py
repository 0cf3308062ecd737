"""The technician's aids onto a reference point, as a part of the ``JogController``: the proximity cue to the
selected point, the planned "go near" (started on confirmation, followed segment by segment as the arm
arrives) and the seat key (``Compliant``: freedrive on a UR). The maths is ``station.tui.approach``; this part
talks to the robot through the controller (its lock, its error handling, its journal)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from station.robot.capabilities import Compliant
from station.robot.errors import ConfigError, LimitError, StationError
from station.tui import approach as ap

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from station.engine.cell import Cell
    from station.engine.session import Session
    from station.kinematics import Model
    from station.kinematics.collision import Checker, KeepOut
    from station.tui.hold import HoldToRun

NEAR_STALL_S = 1.0  # s: a "go near" segment that shows no motion for this long after its command has stopped


class Reading(Protocol):
    T: np.ndarray | None  # the tool pose of the last reading (nominal model), base frame


class Aided(Protocol):
    """What the aids need of the jog controller that owns them (``station.tui.controller.JogController``): the
    robot, its model and cell, the selected point, the last reading, the hold in progress, its lock and session,
    and where it says what happened. Written here, so this part does not import the controller that imports it."""

    robot: Any
    model: Model
    session: Session
    cell: Cell | None
    reference: Any  # "unknown", or {label: xyz} given on the command line
    keep_out: KeepOut
    readout: Reading | None
    holding: HoldToRun
    io_lock: AbstractContextManager
    frame: str
    ur_rotvec: bool
    fault: str | None
    message: str

    @property
    def point(self) -> str: ...

    @property
    def speed_mm_s(self) -> float: ...

    def count_si(self, joint: int) -> float: ...

    def _get_checker(self) -> Checker | None: ...

    def _update_guidance(self) -> None: ...

    def _on_error(self, err: StationError, what: str) -> None: ...


class ApproachAids:
    """Proximity, go near and seat for one controller (``ctl``)."""

    def __init__(self, ctl: Aided) -> None:
        self.ctl = ctl
        # where the technician can be sent: points with a nominal position, and the ones they cannot be
        # (a socket without a compliant mode to seat it; out of reach: checked at the first reading)
        mounting = ctl.keep_out.mounting
        self.targets: dict[str, ap.Target] = ap.targets_of(ctl.cell, ctl.reference,
                                                           None if mounting is None else mounting.normal)
        self.can_seat = isinstance(ctl.robot, Compliant)
        self.blocked: dict[str, str] = {} if self.can_seat else {
            lb: "socket: this robot has no compliant (freedrive) mode to seat the ball"
            for lb, t in self.targets.items() if t.kind == "socket"}
        self._reach_checked = False
        self._reached: set[str] = set()  # points found reachable so far
        self.compliant = False  # as commanded here, or as the robot reports it (freedrive from its pendant)
        self.near: ap.NearMove | None = None  # a running "go near"
        self.near_plan: ap.NearPlan | None = None  # planned, waiting for the technician's confirmation
        self.proximity: ap.Proximity | None = None  # of the tool to the selected point (nominal)

    def reading(self, status, q: np.ndarray) -> None:
        """A new reading (the controller's poll): follow a compliant mode switched behind the UI, update the
        proximity, check the reach once, start the next segment of a go-near."""
        compliant = bool(getattr(status, "compliant", False))
        if self.can_seat and compliant != self.compliant:  # changed behind the UI (pendant, protective stop)
            self.compliant = compliant
        self._update_proximity()
        if not self._reach_checked:
            self._check_reach(q)
        if self.near is not None:
            self._advance_near(status.moving, q)

    def _stiffen(self, quiet: bool = True) -> bool:
        """Leave the compliant mode if it is on (teardown, STOP, fault). True if it was on."""
        c = self.ctl
        if not self.compliant or not self.can_seat:
            return False
        try:
            with c.session.step("compliant off", by="stop"):
                c.robot.set_compliant(False)
        except StationError as e:
            if not quiet:
                c._on_error(e, "compliance off")
            return False
        self.compliant = False
        return True

    @property
    def compliant_name(self) -> str:
        """What the vendor calls the yielding mode (UR: freedrive)."""
        c = self.ctl
        return "freedrive" if c.ur_rotvec else "compliant"

    def _update_proximity(self) -> None:
        c = self.ctl
        target = self.targets.get(c.point)
        r = c.readout
        ok = target is not None and r is not None and r.T is not None
        self.proximity = ap.proximity(r.T, target, c.frame) if ok else None

    def _check_reach(self, q: np.ndarray) -> None:
        """One point per reading (an IK search costs 10-200 ms: spread over the first readings, never during a
        hold): the points the nominal arm cannot bring its tool onto are not offered as the next point (a cell
        laid out for another arm, a point beyond the reach). A parallel robot has no link capsules: skipped."""
        c = self.ctl
        if c.holding.hold_state is not None or self.near is not None:
            return
        todo = [lb for lb in self.targets if lb not in self.blocked and lb not in self._reached]
        if not todo or getattr(c.model, "kind", "serial") == "parallel":
            self._reach_checked = True
            return
        label = todo[0]
        why = ap.reach_problem(c.model, self.targets[label], c._get_checker(), q)
        self._reached.add(label)
        if why is not None:
            self.blocked[label] = why
            c._update_guidance()

    def toggle_compliant(self) -> bool:
        """The seat key: make the arm compliant (UR: freedrive) so a socket's cone can pull the ball in, or
        hold it stiff again. Journaled as a step; refused while moving or faulted."""
        c = self.ctl
        name = self.compliant_name
        if not self.can_seat:
            c.message = (f"this robot has no {name} mode: sockets cannot be seated here; touch needles "
                         "(the contact input) instead")
            return False
        if c.fault:
            c.message = "clear the fault first (c)"
            return False
        on = not self.compliant
        if on and (self.near is not None or c.holding.hold_state is not None):
            c.message = f"robot is moving: wait, or STOP (space), before {name}"
            return False
        with c.io_lock:
            try:
                # asked now, not from the last poll: a move that just ended still reads "moving" there
                if on and c.robot.status().moving:
                    c.message = f"robot is moving: wait, or STOP (space), before {name}"
                    return False
                with c.session.step("compliant on" if on else "compliant off", point=c.point):
                    c.robot.set_compliant(on)
            except ConfigError as e:  # this robot's devices cannot yield (e.g. a servo without current control)
                c.message = f"refused: {e}"
                return False
            except StationError as e:
                c._on_error(e, f"{name} {'on' if on else 'off'}")
                return False
        self.compliant = on
        target = self.targets.get(c.point)
        if on and target is not None and target.kind == "socket":
            c.message = (f"{name} ON: the ball settles into socket {c.point} (guide it in by hand if it "
                         "does not); enter records once CONTACT lights; v holds the arm")
        elif on:
            c.message = f"{name} ON: the arm yields; v holds it stiff again (jogging is refused meanwhile)"
        else:
            c.message = "arm held stiff again: jog clear of the point before the next one"
        return True

    def _near_refusal(self) -> str | None:
        c = self.ctl
        if c.fault:
            return "clear the fault first (c)"
        if getattr(c.model, "kind", "serial") == "parallel":
            return "go near plans with the link capsules of a serial arm: jog a parallel robot by hand"
        if self.compliant:
            return f"the arm is {self.compliant_name}: v holds it stiff first"
        if self.near is not None:
            return f"already going near {self.near.plan.label}: wait, or STOP (space)"
        if c.point not in self.targets:
            return (f"point {c.point} has no nominal position: give it in the cell file (--cell) or as "
                    f"--reference {c.point}=x,y,z")
        return None

    def plan_near(self) -> ap.NearPlan | None:
        """Plan "go near the selected point" (``station.tui.approach.plan_near``): nothing moves until
        :meth:`start_near` is called with the plan (after the technician confirmed it)."""
        c = self.ctl
        self.near_plan = None
        refusal = self._near_refusal()
        if refusal:
            c.message = refusal
            return None
        with c.io_lock:
            try:
                status = c.robot.status()
                q = np.asarray(c.robot.joint_positions().q, float)
            except StationError as e:
                c._on_error(e, "go near")
                return None
        if status.moving or c.holding.hold_state is not None:
            c.message = "robot is moving: wait, or STOP (space)"
            return None
        try:
            plan = ap.plan_near(c.model, c.keep_out, q, self.targets[c.point],
                                c.speed_mm_s * 1e-3, checker=c._get_checker())
        except LimitError as e:
            c.message = f"refused: {e}"
            return None
        self.near_plan = plan
        return plan

    def start_near(self, plan: ap.NearPlan) -> bool:
        """Start a confirmed "go near": its first segment now, the next ones as the arm arrives (``poll``)."""
        c = self.ctl
        self.near_plan = None
        refusal = self._near_refusal()
        if refusal:
            c.message = refusal
            return False
        with c.io_lock:
            try:
                q = np.asarray(c.robot.joint_positions().q, float)
            except StationError as e:
                c._on_error(e, "go near")
                return False
        if np.max(np.abs(q - plan.start)) > 1e-3:  # the arm moved since the plan was made: plan again
            c.message = "the arm moved since the plan was shown: press n again"
            return False
        self.near = ap.NearMove(plan)
        if not self._send_near():
            return False
        c.message = (f"going near {plan.label} at {plan.cap * 1e3:g} mm/s (about {plan.seconds:.0f} s): "
                     "STOP with space or ctrl+c")
        return True

    def _send_near(self) -> bool:
        c = self.ctl
        nm = self.near
        if nm is None:
            return False
        with c.io_lock:
            try:
                c.robot.move_joints(nm.segment, speed=nm.speed, wait=False)
            except LimitError as e:
                self.near = None
                c.message = f"refused: {e}"
                return False
            except StationError as e:
                self.near = None
                c._on_error(e, f"go near {nm.plan.label}")
                return False
        nm.started, nm.seen_moving = time.monotonic(), False
        return True

    def _advance_near(self, moving: bool, q: np.ndarray) -> None:
        c = self.ctl
        nm = self.near
        if moving:
            nm.seen_moving = True
            return
        tol = max(0.01, 10 * max((c.count_si(j) for j in range(c.model.n_joints)), default=0.0))
        if np.max(np.abs(q - nm.segment)) > tol:
            if nm.seen_moving or time.monotonic() - nm.started > NEAR_STALL_S:
                self.near = None
                c.message = f"go near {nm.plan.label}: the arm stopped short of the target"
            return
        if not nm.last:
            nm.index += 1
            self._send_near()
            return
        self.near = None
        c.message = (f"near {nm.plan.label}: {nm.plan.standoff * 1e3:g} mm out along its approach; jog in with "
                     "steps (3: 1 mm, 2: 0.1 mm) watching the distance")
