"""The jog UI's logic, apart from any widget: step presets, speed override, jogging through the shared
motion helpers, the touch indicator, seating (compliance), record/retake/discard into the session, faults
and write-back. Textual widgets only render this state and call these methods (and tests can too).

Parts live in their own modules and are reached through the controller: hold-to-run (``station.tui.hold``),
the proximity cue and "go near" (``station.tui.approach``), the live solve (``station.tui.livesolve``) and the
progress guidance (``station.tui.guidance``)."""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from station.engine import events as ev
from station.engine.cell import Cell
from station.engine.session import Session
from station.engine.writeback import (
    WriteBackError,
    WritebackPlan,
    apply,
    corrections_of,
    count_tolerance,
    plan_restore,
    plan_write,
)
from station.kinematics import Model, se3
from station.kinematics.collision import Checker, KeepOut
from station.robot.capabilities import CalibrationExport, CalibrationStore, ContactSensor, VelocityJog
from station.robot.errors import LimitError, StationError
from station.robot.motion import MANUAL_TOOL_SPEED_CAP, jog_target, joint_speed_for_tool_cap
from station.tui import approach as ap
from station.tui import guidance as gd
from station.tui.aids import ApproachAids
from station.tui.hold import (  # noqa: F401  (the hold-to-run constants, importable from here as before)
    HOLD_CHECK_S,
    HOLD_DELAY_MIN_S,
    HOLD_FIRST_S,
    HOLD_GAP_MIN_S,
    HOLD_GAP_REPEATS,
    HOLD_RELEASE_S,
    HOLD_TICK_S,
    HOLD_WATCHDOG_S,
    RELEASE_LOCK_S,
    HoldToRun,
)
from station.tui.livesolve import SolveState, is_forced, live_solve

STEP_PRESETS = (0.01, 0.1, 1.0, 10.0)  # mm for translations / prismatic joints, deg for rotations
SPEED_PERCENT = (1, 2, 5, 10, 25, 50, 100)  # speed override, % of the manual tool-speed cap (250 mm/s)
POINT_LABELS = tuple("ABCDEFGH")
CART_AXES = ("X", "Y", "Z", "Rx", "Ry", "Rz")
JOG_MAX_JOINT_SPEED = ap.NEAR_JOINT_SPEED  # rad/s (m/s prismatic): manual jog never faster than this per joint
STOP_LOCK_S = 0.2  # s: a STOP key on the terminal's input thread waits at most this for a robot call in flight


def _part_attr(part: str, name: str) -> property:
    """An attribute of one of the controller's parts, reachable on the controller itself."""
    return property(lambda self: getattr(getattr(self, part), name),
                    lambda self, v: setattr(getattr(self, part), name, v))


def _hold_attr(name: str) -> property:
    """An attribute of the hold-to-run part, reachable on the controller as before the split."""
    return _part_attr("holding", name)


@dataclass
class Readout:
    q: np.ndarray  # SI
    tcp: np.ndarray  # (6,) x, y, z (m), rx, ry, rz (rad) of the nominal model: roll-pitch-yaw, or UR's rotation vector
    touch: bool | None
    moving: bool
    enabled: bool
    t: float
    compliant: bool = False  # the robot reports a yielding mode (freedrive / low torque)
    T: np.ndarray | None = None  # 4x4 tool pose of the nominal model


@dataclass
class ExportPlan:
    """A controller that keeps its calibration itself (UR): the write-back is an export of files into
    ``folder``; the controller is unchanged, so there is no before/after and nothing to restore."""

    folder: Path
    corrections: dict[str, float]
    kind: str = "export"


def parse_reference(specs: str | list[str] | None) -> str | dict[str, np.ndarray]:
    """``--reference`` as ``station solve`` takes it: ``unknown``, ``x,y,z`` (point A) or ``LABEL=x,y,z``
    (repeatable), metres unless one unit suffix follows the three numbers (``100,200,50mm``)."""
    from station.robot.errors import ConfigError
    from station.units import LENGTH_UNITS

    items = [specs] if isinstance(specs, str) else list(specs or [])
    items = [s.strip() for s in items if s and s.strip()]
    if not items or items == ["unknown"]:
        return "unknown"
    ref: dict[str, np.ndarray] = {}
    for spec in items:
        label, _, xyz = spec.rpartition("=")
        label = label.strip() or POINT_LABELS[0]
        m = re.fullmatch(r"\s*([^,]+),([^,]+),([^,a-zA-Z]+?)\s*([a-zA-Z]+)?\s*", xyz)
        try:
            if spec == "unknown" or not m or (m.group(4) or "m") not in LENGTH_UNITS:
                raise ValueError
            v = np.array([float(m.group(k)) for k in (1, 2, 3)]) * LENGTH_UNITS[m.group(4) or "m"]
            if not np.all(np.isfinite(v)):
                raise ValueError
        except ValueError:
            raise ConfigError(f"--reference {spec!r}: expected unknown, x,y,z or LABEL=x,y,z in metres "
                              "(or with a unit suffix like 100,200,50mm)") from None
        ref[label] = v
    return ref


class JogController:
    """One robot, one session. The UI calls everything from its own thread; ``io_lock`` only protects callers
    that use the controller from other threads too. ``stop()`` deliberately bypasses the lock."""

    def __init__(self, robot, session: Session, *, model: Model | None = None, identify: str = "offsets,tcp",
                 reference: str | dict = "unknown", cell: Cell | None = None, limits: dict | None = None,
                 limits_version: str | None = None, judged_as: str = "jog") -> None:
        self.robot = robot
        self.model: Model = model if model is not None else robot.model
        self.session = session  # the engine session in technician mode (station.engine.runner.technician_session)
        session.steps.on_lost = self._trace_lost  # a full disk never holds back an action the technician asked for
        self.identify = identify
        self.reference = reference
        self.cell = cell
        self.keep_out: KeepOut = cell.keep_out if cell is not None else KeepOut.default()
        self._checker: Checker | None = None
        self.limits = dict(limits or {})  # name -> station.engine.limits.Limit; empty: verdict NO LIMITS
        self.limits_version = limits_version
        self.judged_as = judged_as  # the limits section (procedure name) that judges this session
        self.io_lock = threading.RLock()
        self.mode = "joint"  # joint | cartesian
        self.frame = "base"  # base | tool: the frame of Cartesian jogs
        self.continuous = False  # hold-to-run instead of one step per key
        self.axis = 0  # last axis jogged / selected
        self.step_index = 1
        self.speed_index = 3
        self.labels = self._point_labels()
        # points to guide through: the cell's and the known references'; free labels A..H are only names
        self.guided = cell is not None or isinstance(reference, dict)
        self.point_index = 0
        self.numbers: dict[int, int] = {}  # journal seq -> sample number 1..n in this session
        self.holding = HoldToRun(self)
        self.predicted: dict[str, float | None] = {}
        self.aids = ApproachAids(self)  # proximity cue, go near, seat key (station.tui.aids)
        self.stop_mark = 0.0  # monotonic time of the last STOP: key events that arrived before it are dropped
        self.guide: gd.Guidance = gd.guidance(self.model, self._guide_labels(), [], None, self.limits, None,
                                              self.aids.blocked)
        self.verdict: dict | None = None
        self.ur_rotvec = isinstance(robot, CalibrationExport)  # UR pendant shows the rotation vector
        # hold-to-run re-targets position moves, except on a robot with a velocity jog (UR: speedJ/speedL
        # under its RTDE watchdog), where re-targeting moveJ would re-plan and brake on every command
        # (measured 8 of 25 mm/s, 0.5 s late stop): there each tick re-sends the speed instead
        self.velocity_jog = isinstance(robot, VelocityJog)
        self.hold_supported = True
        self.selected: int | None = None  # index into session.samples(); None = the latest
        self.fault: str | None = None
        self.message = "ready"
        self.readout: Readout | None = None
        self.stale = False  # the last poll failed: the readout shows the last known values
        self.solve_state = SolveState()
        self.writeback_done: dict | None = None
        self.exported: list[str] = []  # files of the last export (controllers that keep their own calibration)
        self.writeback_failed = False  # a write-back raised or did not read back: W then offers the restore
        self.pre_image: dict[str, float] = {}  # the device calibration before this session's first write-back
        self.last_jog: dict | None = None
        self.closed = False
        self.model.select(identify)  # unknown group/name: fail at start, not after the first record

    # ---- presets ---------------------------------------------------------------------------------------
    @property
    def step(self) -> float:
        return STEP_PRESETS[self.step_index]

    @property
    def speed_percent(self) -> int:
        return SPEED_PERCENT[self.speed_index]

    @property
    def speed_mm_s(self) -> float:
        return MANUAL_TOOL_SPEED_CAP * 1e3 * self.speed_percent / 100.0

    @property
    def point(self) -> str:
        return self.labels[self.point_index]

    def _point_labels(self) -> list[str]:
        """Selectable labels: the cell's points, then ``--reference`` labels not in the cell; A..H without either."""
        labels = list(self.cell.points) if self.cell is not None else []
        if isinstance(self.reference, dict):
            labels += [lb for lb in self.reference if lb not in labels]
        return labels or list(POINT_LABELS)

    def set_step(self, index: int) -> None:
        self.stop_hold()
        self.continuous = False
        self.step_index = max(0, min(len(STEP_PRESETS) - 1, index))
        self.message = f"step {self.step:g} mm / deg per key"

    def set_continuous(self) -> None:
        if not self.hold_supported:
            self.message = "hold-to-run is not available on this robot yet: use the step presets 1-4"
            return
        self.continuous = True
        self.message = (f"hold-to-run: hold a jog key to move at {self.speed_percent} % "
                        f"({self.speed_mm_s:g} mm/s at the tool); release to stop")

    def change_speed(self, delta: int) -> None:
        self.speed_index = max(0, min(len(SPEED_PERCENT) - 1, self.speed_index + delta))
        self.message = f"speed override {self.speed_percent} % = {self.speed_mm_s:g} mm/s at the tool"

    def toggle_mode(self) -> None:
        self.stop_hold()
        self.mode = "cartesian" if self.mode == "joint" else "joint"
        self.message = f"{self.mode} jog" + (f" ({self.frame} frame)" if self.mode == "cartesian" else "")

    def toggle_frame(self) -> None:
        self.stop_hold()
        self.frame = "tool" if self.frame == "base" else "base"
        self.message = f"Cartesian jogs in the {self.frame} frame"
        self._update_proximity()

    def next_point(self, delta: int = 1) -> None:
        self.point_index = (self.point_index + delta) % len(self.labels)
        target = self.targets.get(self.point)
        self.message = f"reference point {self.point}" + (f" ({target.kind})" if target is not None else "")
        if self.point in self.blocked:
            self.message += f": {self.blocked[self.point]}"
        elif target is not None:
            self.message += ": n goes near it"
        self._update_proximity()

    def number(self, sample: ev.Sample) -> int:
        """The sample's number in this session, 1..n in recording order (not the journal's sequence)."""
        return self.numbers.get(sample.seq, 0)

    def axis_names(self) -> list[str]:
        if self.mode == "cartesian":
            return list(CART_AXES)
        return [f"J{i + 1}" for i in range(self.model.n_joints)]

    def axis_unit(self, axis: int) -> str:
        if self.mode == "joint":
            rotational = self.model.joints[axis].revolute if axis < self.model.n_joints else True
        else:
            rotational = axis >= 3
        return "deg" if rotational else "mm"

    def joint_rate(self, axis: int) -> float:
        """Lead-joint speed limit of a jog on ``axis`` (rad/s, m/s prismatic); the tool-speed cap at the
        override applies on top. A Cartesian rotation (the TCP stands still, so the tool cap does not bite)
        turns at the override's share of 30 deg/s, as a pendant's speed slider scales it."""
        if self.mode == "cartesian" and axis >= 3:
            return JOG_MAX_JOINT_SPEED * self.speed_percent / 100.0
        return JOG_MAX_JOINT_SPEED

    def lead_rate(self, axis: int, q0: np.ndarray, target: np.ndarray, step: float) -> float:
        """Lead-joint speed limit for a move from ``q0`` to ``target`` (one ``step`` on ``axis``): for a
        Cartesian rotation the one that turns the tool at :meth:`joint_rate` (the lead joint may turn faster
        or slower than the tool), else :meth:`joint_rate`."""
        rate = self.joint_rate(axis)
        if self.mode == "cartesian" and axis >= 3 and abs(step) > 0:
            rate *= float(np.max(np.abs(target - q0))) / abs(step)
        return rate

    def step_si(self, axis: int) -> float:
        """The current preset in SI for ``axis`` of the current mode."""
        return np.deg2rad(self.step) if self.axis_unit(axis) == "deg" else self.step * 1e-3

    # ---- robot I/O -------------------------------------------------------------------------------------
    def _on_error(self, err: StationError, what: str) -> None:
        """A bus/device/safety error: stop, show it, journal it. A refused command (LimitError) is not a
        fault: nothing was sent, so the UI only says why."""
        if isinstance(err, LimitError):
            self.message = f"refused: {err}"
            return
        self.message = "FAULT: motion stopped"
        if self.fault is not None:  # already stopped and journaled; polling keeps failing until reset
            return
        self.fault = f"{what}: {err}"
        self.stop(quiet=True)
        try:
            self.session.event(ev.Fault(step=what, error=type(err).__name__, message=str(err)))
        except Exception as e:  # the journal is gone too (disk full): keep the banner, say so
            self.fault += f" (journal: {e})"

    def stop(self, quiet: bool = False) -> None:
        """Always available: no lock, no precondition. Ends a hold and a "go near"; a compliant arm is held
        stiff again (STOP means: hold where you are)."""
        self.holding._end_hold()
        near, self.near = self.near, None
        try:
            self.robot.stop()
        except StationError as e:
            if not quiet:
                self._on_error(e, "stop")
            return
        held = self.aids._stiffen(quiet)
        if not quiet:
            self.message = "STOPPED" + (f": go near {near.plan.label} cancelled" if near else "") + (
                "; arm held stiff again" if held else "")

    def stop_now(self) -> None:
        """A STOP key (space, x, ctrl+c). The app calls it on the terminal's input thread as soon as the key is
        parsed, ahead of the key events queued for the UI (a UI busy in a solve or a redraw would serve it
        late), and again on the UI thread. A robot call in flight is waited for (``io_lock``, at most
        STOP_LOCK_S); if it does not finish, a velocity-jog robot is stopped anyway (as a key release is), a
        position-controlled one (bus not thread-safe) by the UI thread. Key events that arrived before the STOP
        start no motion afterwards (``stop_mark``)."""
        self.stop_mark = time.monotonic()
        locked = self.io_lock.acquire(timeout=STOP_LOCK_S)
        try:
            if locked or self.velocity_jog:
                self.stop()
        finally:
            if locked:
                self.io_lock.release()

    def _trace_lost(self, name: str, err: Exception) -> None:
        """A step's event could not be journaled (disk full): the banner says so, the robot still obeys (the
        journal lists the lost event: the session cannot pass)."""
        self.message = f"{name} (not journaled: {err})"

    def poll(self, block: bool = False) -> Readout | None:
        """Refresh joints, TCP, touch and status (and the proximity cue; a running "go near" starts its next
        segment here). Skips (returns None) while another thread talks to the robot unless ``block``."""
        if not self.io_lock.acquire(blocking=block):
            return None
        try:
            snap = self.robot.joint_positions()
            touch = self.robot.touch() if isinstance(self.robot, ContactSensor) else None
            status = self.robot.status()
        except StationError as e:
            self.stale = True
            self._on_error(e, "read")
            return None
        finally:
            self.io_lock.release()
        self.stale = False
        if not status.ok and self.fault is None:
            parts = list(status.faults)
            if status.estop:
                parts.append("emergency stop")
            if status.protective_stop:
                parts.append("protective stop")
            self.fault = "robot reports: " + "; ".join(parts)
            self.message = "FAULT: motion stopped"
            self.stop(quiet=True)
            self.session.event(ev.Fault(step="status", error="status", message=self.fault))
        q = np.asarray(snap.q, float)
        T = self.model.fk(q)
        rot = se3.matrix_to_rotvec(T[:3, :3]) if self.ur_rotvec else se3.matrix_to_rpy(T[:3, :3])
        tcp = np.concatenate([T[:3, 3], rot])
        self.readout = Readout(q, tcp, touch, status.moving, status.enabled, snap.t,
                               bool(getattr(status, "compliant", False)), T)
        self.aids.reading(status, q)
        return self.readout

    def _get_checker(self) -> Checker | None:
        if self._checker is None:  # built once: the envelope compile is the expensive part
            if getattr(self.model, "kind", "serial") == "parallel":
                return None  # a parallel model has no link capsules (as in the planner): joint limits only
            self._checker = Checker(self.model, self.keep_out)
        return self._checker

    def quit_concerns(self) -> list[str]:
        """What quitting now would do beyond closing an idle session (the app asks before it does)."""
        out = []
        r = self.readout
        if self.near is not None or self.holding.hold_state is not None or (r is not None and r.moving):
            out.append("the robot is moving: it stops")
        if self.compliant:
            out.append(f"the arm is {self.compliant_name}: it is held stiff")
        n = len(self.session.samples())
        if n:
            verdict = {"good enough": "PASS expected", "NO LIMITS": "verdict NO LIMITS"}.get(
                self.guide.status, "FAIL expected: not good enough yet")
            out.append(f"the session ends with {n} sample{'s' if n != 1 else ''} ({verdict}); no more can be added")
        forced = self.solve_state.forced
        if forced:
            out.append(f"{forced} forced sample{'s' if forced != 1 else ''} (no contact) "
                       f"{'are' if forced != 1 else 'is'} still in it: the session cannot pass")
        if (self.solve_state.result is not None and self.writeback_done is None and not self.exported
                and self.solve_state.identified_ok and corrections_of(self.solve_state.result)):
            out.append("the identified offsets are not written back (W)")
        return out

    def _refuse_axis(self, axis: int) -> str | None:
        if self.fault:
            return "clear the fault first (c)"
        if self.compliant:
            return f"the arm is {self.compliant_name}: v holds it stiff before jogging"
        if self.near is not None:
            return f"going near {self.near.plan.label}: wait, or STOP (space)"
        if self.mode == "joint" and axis >= self.model.n_joints:
            return f"this robot has {self.model.n_joints} joints"
        if self.mode == "cartesian" and axis >= 3 and self.model.n_joints < 6:
            # the IK solves position only below 6 joints: a rotation step would silently do nothing
            return f"a {self.model.n_joints}-joint arm jogs its tool position only: use joint mode to turn it"
        return None

    def count_si(self, joint: int) -> float:
        """One encoder count of ``joint`` in SI (0 when the model has no device scaling)."""
        enc = self.model.joints[joint].encoder
        return 0.0 if enc is None else 1.0 / (enc.counts_per_unit * enc.gear)

    def target(self, q0: np.ndarray, axis: int, step: float) -> np.ndarray:
        """Joint target of one step (SI) on ``axis`` in the current mode and frame; LimitError when it is
        unreachable, outside joint limits, or brings a link into the cell's keep-out (checked along the path)."""
        if self.mode == "joint" or self.frame == "base":
            target = jog_target(self.model, q0, self.mode, axis, step)
        else:
            target = self._tool_frame_target(q0, axis, step)
        checker = self._get_checker()
        if checker is None:
            return target
        hit = checker.path_hit(q0, target)
        if hit is not None:  # the same words as station.engine.cell.check_path_clear
            raise LimitError(f"jog: {hit.describe()} on the way; refused")
        return target

    def _tool_frame_target(self, q0: np.ndarray, axis: int, step: float) -> np.ndarray:
        from station.robot.motion import check_joint_limits

        T = self.model.fk(q0)
        goal = T.copy()
        R = T[:3, :3]
        if axis < 3:
            goal[:3, 3] += R[:, axis] * step  # along the tool's own axis
        else:
            rv = np.zeros(3)
            rv[axis - 3] = step
            goal[:3, :3] = R @ se3.rotvec_to_matrix(rv)  # about the tool's own axis, through the TCP
        full = self.model.n_joints >= 6
        res = self.model.ik(goal if full else goal[:3, 3], q0, position_only=not full or None)
        if not res.ok[0]:
            raise LimitError(f"jog: tool-frame step {step:g} on axis {'xyz'[axis % 3]} is not reachable within "
                             "joint limits from here")
        return check_joint_limits(self.model, res.q[0], "jog")

    def jog(self, axis: int, direction: int) -> bool:
        """One step of the current preset on ``axis`` (joint index or 0..5 = X Y Z Rx Ry Rz), sign from
        ``direction``. A key pressed while the previous step still runs extends that move by one more step
        from its target (no press is dropped). Refused with a message, nothing sent: a step below one
        encoder count, a target outside joint limits or unreachable, a link entering the keep-out. The move
        is started without waiting, so the UI thread stays free for STOP and every bus transaction stays on
        one thread (the Dynamixel SDK port is not thread-safe)."""
        refusal = self._refuse_axis(axis)
        if refusal:
            self.message = refusal
            return False
        if self.continuous:
            return self.hold(axis, direction)
        self.axis = axis
        step = float(np.sign(direction)) * self.step_si(axis)
        if self.mode == "joint" and abs(step) < self.count_si(axis) * (1 - 1e-9):
            c = self.count_si(axis)
            unit, k = ("deg", 180 / np.pi) if self.model.joints[axis].revolute else ("mm", 1e3)
            self.message = (f"refused: a {self.step:g} {self.axis_unit(axis)} step is below one encoder count of "
                            f"J{axis + 1} ({c * k:.4g} {unit}); choose a larger step")
            return False
        cap = self.speed_mm_s * 1e-3
        with self.io_lock:
            try:
                status = self.robot.status()
                q0 = np.asarray(self.robot.joint_positions().q, dtype=float)
                start = q0
                last = self.last_jog
                same = (last is not None and last["mode"] == self.mode and last["axis"] == axis
                        and last.get("frame") == self.frame and np.sign(last["step"]) == np.sign(step)
                        and not last.get("hold"))
                if status.moving and same and np.max(np.abs(last["target"] - q0)) > last["step_dq"] * 1.05:
                    # at most one step queued: a held step key (terminal repeats) must not pile up travel
                    # that continues long after the key is released
                    self.message = "one step already queued: wait, or STOP (space)"
                    return False
                if status.moving and same:
                    start = np.asarray(last["target"], float)  # queued: one more step from where it is going
                elif status.moving:
                    self.message = "still moving: wait, or STOP (space)"
                    return False
                target = self.target(start, axis, step)  # LimitError: nothing sent
                if self.mode == "cartesian" and np.all(np.abs(target - start) < [
                        self.count_si(j) for j in range(self.model.n_joints)]):
                    self.message = (f"refused: a {self.step:g} {self.axis_unit(axis)} Cartesian step moves no joint "
                                    "by one encoder count; choose a larger step")
                    return False
                # lead-joint speed that keeps the tool at or below the override along the whole step; the
                # joint cap keeps wrist rotations (tool point nearly still) from snapping round
                speed = joint_speed_for_tool_cap(self.model, q0, target, self.lead_rate(axis, start, target, step),
                                                 cap=cap)
                self.robot.move_joints(target, speed=speed, wait=False)
            except LimitError as e:
                self.message = f"refused: {e}"
                return False
            except StationError as e:
                self._on_error(e, f"jog {self.axis_names()[axis]}")
                return False
        self.last_jog = {"mode": self.mode, "frame": self.frame, "axis": axis, "step": step, "speed": speed,
                         "q0": q0, "target": target, "cap_m_s": cap,
                         "step_dq": float(np.max(np.abs(target - start)))}
        self.message = (f"jog {self.axis_names()[axis]} {'+' if step > 0 else '-'}{self.step:g} {self.axis_unit(axis)}"
                        + (f" ({self.frame} frame)" if self.mode == "cartesian" else ""))
        return True

    # ---- hold-to-run (station.tui.hold) --------------------------------------------------------------
    hold_state = _hold_attr("hold_state")
    repeat_intervals = _hold_attr("repeat_intervals")
    repeat_delay = _hold_attr("repeat_delay")
    release_events = _hold_attr("release_events")
    key_arrivals = _hold_attr("key_arrivals")

    def hold(self, axis: int, direction: int, now: float | None = None) -> bool:
        return self.holding.hold(axis, direction, now)

    def release(self, axis: int, direction: int) -> None:
        self.holding.release(axis, direction)

    def hold_check(self, now: float | None = None) -> bool:
        return self.holding.hold_check(now)

    def hold_tick(self, now: float | None = None) -> None:
        self.holding.hold_tick(now)

    def hold_idle(self, now: float | None = None) -> None:
        if not self.compliant:  # no keep-alive for a jog watchdog while the arm is in freedrive
            self.holding.hold_idle(now)

    def stop_hold(self, quiet: bool = False) -> None:
        self.holding.stop_hold(quiet)

    def release_gap(self) -> float:
        return self.holding.release_gap()

    def first_window(self) -> float:
        return self.holding.first_window()

    # ---- proximity, go near, seat (station.tui.aids) -------------------------------------------------------
    targets = _part_attr("aids", "targets")
    blocked = _part_attr("aids", "blocked")
    can_seat = _part_attr("aids", "can_seat")
    compliant = _part_attr("aids", "compliant")
    near = _part_attr("aids", "near")
    near_plan = _part_attr("aids", "near_plan")
    proximity = _part_attr("aids", "proximity")

    @property
    def compliant_name(self) -> str:
        return self.aids.compliant_name

    def toggle_compliant(self) -> bool:
        return self.aids.toggle_compliant()

    def plan_near(self) -> ap.NearPlan | None:
        return self.aids.plan_near()

    def start_near(self, plan: ap.NearPlan) -> bool:
        return self.aids.start_near(plan)

    def _update_proximity(self) -> None:
        self.aids._update_proximity()

    def enable(self) -> None:
        """Reset a fault: re-enable the robot and clear the banner only if the robot then reports OK."""
        with self.io_lock:
            try:
                with self.session.step("enable"):
                    self.robot.enable()
                    status = self.robot.status()
            except StationError as e:
                self.fault = f"enable: {e}"
                return
        if status.ok:
            self.fault = None
            self.message = "enabled"
        else:
            self.fault = "still faulted: " + "; ".join(status.faults or ("stop input active",))

    # ---- samples ---------------------------------------------------------------------------------------
    def _selected_sample(self) -> ev.Sample | None:
        samples = self.session.samples()
        if not samples:
            return None
        i = len(samples) - 1 if self.selected is None else max(0, min(len(samples) - 1, self.selected))
        return samples[i]

    def select(self, delta: int) -> None:
        n = len(self.session.samples())
        if not n:
            return
        cur = n - 1 if self.selected is None else self.selected
        cur = max(0, min(n - 1, cur + delta))
        self.selected = None if cur == n - 1 else cur

    def record(self, force: bool = False, point: str | None = None) -> ev.Sample | None:
        """Record the current pose as a touch of the selected reference point. Refused while faulted, moving,
        or (unless ``force``) while the cell's contact input is present and not lit."""
        if self.fault:
            self.message = "clear the fault first (c)"
            return None
        if self.writeback_done is not None or self.writeback_failed:
            self.message = "calibration was written back: start a new session to verify (samples would mix)"
            return None
        with self.io_lock:
            try:
                status = self.robot.status()
                touch = self.robot.touch() if isinstance(self.robot, ContactSensor) else None
                snap = self.robot.joint_positions()
            except StationError as e:
                self._on_error(e, "record")
                return None
        if not status.ok:
            self.message = "robot not OK: not recorded"
            return None
        if status.moving:
            self.message = "robot is moving: not recorded"
            return None
        if touch is False and not force:
            self.message = "no contact: jog onto the reference until the touch indicator lights (! records anyway)"
            return None
        try:  # the technician's touches are numbered in recording order (retakes included)
            sample = self.session.add_sample(
                snap, point or self.point, pose=len(self.numbers),
                status={"enabled": status.enabled, "forced": bool(force and touch is False),
                        "compliant": self.compliant, "touch": touch})
        except StationError as e:  # a joint reading that is not finite: a device fault, nothing journaled
            self._on_error(e, "record")
            return None
        self.numbers[sample.seq] = len(self.numbers) + 1
        self.selected = None
        n = len(self.session.samples())
        self.message = f"recorded #{self.number(sample)} on {sample.point} ({n} sample{'s' if n != 1 else ''})"
        if is_forced(sample):
            self.message += ": FORCED without contact, a pose and not a touch (retake it on contact)"
        elif self.compliant:
            self.message += f": v holds the arm, then jog clear of {sample.point}"
        self.solve()
        if self.guided and self.guide.next_point in self.labels and point is None:
            self.point_index = self.labels.index(self.guide.next_point)  # suggest the next point to touch
            self._update_proximity()
        return sample

    def retake(self, force: bool = False) -> ev.Sample | None:
        """Record the current pose in place of the selected sample (same point); the old one is discarded only
        after the new one is safely journaled."""
        old = self._selected_sample()
        if old is None:
            self.message = "nothing to retake"
            return None
        new = self.record(force=force, point=old.point)
        if new is None:
            return None
        self.session.discard(old, reason=f"retaken as #{new.seq}")
        self.message = f"retook #{self.number(old)} as #{self.number(new)} on {new.point}"
        self.solve()
        return new

    def selected_sample(self) -> ev.Sample | None:
        """The sample retake and discard act on: the selected one, else the newest."""
        return self._selected_sample()

    def discard(self) -> ev.Sample | None:
        old = self._selected_sample()
        if old is None:
            self.message = "nothing to discard"
            return None
        self.session.discard(old, reason="technician")
        self.selected = None
        self.message = f"discarded #{self.number(old)}"
        self.solve()
        return old

    # ---- live solve ------------------------------------------------------------------------------------
    def solve(self) -> SolveState:
        """The live solve of the kept samples (``station.tui.livesolve``), then the guidance's prediction."""
        samples = self.session.samples()
        self.predicted = {}
        self.solve_state = live_solve(self.model, samples, self.identify, self.reference)
        if self.limits and self.solve_state.status == "ok":
            q = np.array([s.q for s in samples])
            labels = np.array([s.point for s in samples], dtype=object)
            try:
                self.predicted = gd.predicted_std(self.model, q, labels, self.identify, self.reference)
            except (ValueError, KeyError, np.linalg.LinAlgError):
                self.predicted = {}
        self._update_guidance()
        return self.solve_state

    def _update_guidance(self) -> None:
        self.guide = gd.guidance(self.model, self._guide_labels(), self.session.samples(), self.solve_state.result,
                                 self.limits, self.predicted, self.blocked)

    def _guide_labels(self) -> list[str]:
        return list(self.labels) if getattr(self, "guided", False) else []

    def solve_command(self) -> str:
        """The ``station solve`` line for this session's samples, with everything the live solve used."""
        import shlex

        parts = ["station", "solve", "--model", self.model.name, "--samples", str(self.session.samples_csv),
                 "--identify", self.identify]
        if isinstance(self.reference, dict):
            for label, xyz in self.reference.items():
                parts += ["--reference", f"{label}={','.join(f'{v:.6g}' for v in xyz)}"]
        else:
            parts += ["--reference", str(self.reference)]
        return " ".join(shlex.quote(p) for p in parts)

    # ---- write-back ------------------------------------------------------------------------------------
    def writeback_plan(self) -> WritebackPlan | ExportPlan | None:
        """Before/after of the device's zero offsets (``station.engine.writeback.plan_write``: ``after = before +
        identified offset``); after a failed write-back, the plan restores the pre-image instead."""
        if self.fault:
            self.message = "clear the fault first (c)"
            return None
        if self.writeback_failed:
            before = self._read_calibration()
            return None if before is None else plan_restore(before, self.pre_image)
        if self.writeback_done is not None:
            self.message = "already written back in this session: start a new session to verify"
            return None
        result = self.solve_state.result
        if result is None:
            self.message = "nothing to write back: record samples until the solve identifies offsets"
            return None
        corr = corrections_of(result)
        if isinstance(self.robot, CalibrationExport):  # checked first: UR's write_calibration exports too
            return ExportPlan(self.session.folder / "controller-calibration", corr)
        if not corr:
            self.message = "the solve identified no joint offsets: nothing to write back"
            return None
        before = self._read_calibration()
        if before is None:
            return None
        return plan_write(before, corr)

    def _read_calibration(self) -> dict[str, float] | None:
        if not isinstance(self.robot, CalibrationStore):
            self.message = "this robot stores no joint calibration the station can write"
            return None
        with self.io_lock:
            try:
                return {k: float(v) for k, v in self.robot.read_calibration().items()}
            except StationError as e:
                self._on_error(e, "read calibration")
                return None

    def export_apply(self, plan: ExportPlan) -> bool:
        """Only after the technician confirmed: write the controller's calibration files into ``plan.folder``
        and journal it (``writeback`` phase ``exported`` with the files). The controller is not touched."""
        result = self.solve_state.result
        if result is None:
            self.message = "nothing to export"
            return False
        self.session.event(ev.Result(result=result.to_dict()))
        with self.io_lock:
            try:
                files = [str(p) for p in self.robot.export_calibration(result, plan.folder) or []]
            except (StationError, OSError) as e:
                self.message = f"export failed: {e}; controller unchanged"
                self.session.event(ev.Writeback(phase="failed", error=str(e), note="export; controller unchanged"))
                return False
        self.exported = files
        self.session.event(ev.Writeback(phase="exported", files=files,
                                        note=f"exported to {plan.folder}, controller unchanged"))
        self.message = f"exported to {plan.folder}, controller unchanged"
        return True

    def writeback_apply(self, plan: WritebackPlan | ExportPlan) -> bool:
        """Only after the technician confirmed ``plan``: the engine's two-phase write-back
        (``station.engine.writeback.apply``: pre-image journaled and backed up, write, read back). A failure
        leaves the restore plan armed. Returns whether the device reads back what was written."""
        if isinstance(plan, ExportPlan):
            return self.export_apply(plan)
        restore = plan.kind == "restore"
        note = "restore of the pre-image after a failed write-back" if restore else "technician write-back"
        if not restore:
            result = self.solve_state.result
            if result is not None:
                self.session.event(ev.Result(result=result.to_dict()))
            self.pre_image = dict(plan.before)
        with self.io_lock:
            try:
                self.robot.stop()  # a jog may still be moving; nothing has been written yet
            except StationError as e:
                self._on_error(e, "restore" if restore else "write-back")
                return False
            try:
                apply(self.robot, plan, event=self.session.event, folder=self.session.folder,
                      session=self.session.id, tolerance=self._tolerance, note=note)
            except WriteBackError:
                self.writeback_failed = True
                self.writeback_done = {"before": plan.before, "after": plan.after, "verified": False}
                self.message = "the read-back differs from what was written: W restores the calibration from before"
                return False
            except StationError as e:
                self._on_error(e, "restore" if restore else "write-back")
                self.writeback_failed = True
                self.message = ("FAULT during write-back: the robot may be partly written. Clear the fault (c), "
                                "then W restores the calibration from before")
                return False
        if restore:
            self.writeback_failed = False
            self.writeback_done = None
            self.message = "restored the calibration from before the write-back; recording continues"
        else:
            self.writeback_done = {"before": plan.before, "after": plan.after, "verified": True}
            self.message = "written back and read back OK"
        return True

    def _tolerance(self, name: str) -> float:
        """One encoder count of the joint behind ``offset.jN`` (devices store whole counts), SI."""
        return count_tolerance(self.model, name, 1.0)

    # ---- end -------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Teardown: stop motion whatever happened, journal the final result and the end. Idempotent."""
        if self.closed:
            return
        self.closed = True
        self.stop(quiet=True)
        passed = None
        try:
            result = self.solve_state.result
            if result is not None and self.writeback_done is None:
                self.session.event(ev.Result(result=result.to_dict()))
            # the verdict against the limits that judge this session; none: NO LIMITS, never a PASS
            kept = self.session.samples()
            measured = gd.measurements(self.model, result, len(kept), self.predicted,
                                       sum(is_forced(s) for s in kept))
            self.verdict = gd.judge(self.limits, measured, self.limits_version)
            self.session.event(ev.Verdict(**self.verdict))
            self.session.verdict = self.verdict
            passed = self.verdict["passed"]
        finally:
            # "completed" (the engine's word) also tells station resume there is nothing to do
            self.session.end("completed", passed)

    @property
    def verdict_text(self) -> str:
        """PASS / FAIL / NO LIMITS of the closed session ("" before)."""
        if self.verdict is None:
            return ""
        return self.verdict.get("status") or ("PASS" if self.verdict["passed"] else "FAIL")
