"""The jog UI's logic, apart from any widget: step presets, speed override, jogging through the shared
motion helpers, the touch indicator, record/retake/discard into the session, the live solve, faults and
write-back. Textual widgets only render this state and call these methods (and tests can too)."""

from __future__ import annotations

import re
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.engine import events as ev
from station.engine.cell import Cell
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
from station.tui import guidance as gd
from station.tui.session import JogSession

STEP_PRESETS = (0.01, 0.1, 1.0, 10.0)  # mm for translations / prismatic joints, deg for rotations
SPEED_PERCENT = (1, 2, 5, 10, 25, 50, 100)  # speed override, % of the manual tool-speed cap (250 mm/s)
POINT_LABELS = tuple("ABCDEFGH")
CART_AXES = ("X", "Y", "Z", "Rx", "Ry", "Rz")
JOG_MAX_JOINT_SPEED = np.deg2rad(30.0)  # rad/s (m/s prismatic): manual jog never faster than this per joint
# hold-to-run (docs/jog.md "Hold-to-run"). A terminal with the kitty keyboard protocol reports the key release
# (station.tui.keys): the release stops at once. Elsewhere only the autorepeat shows a held key: the press, a
# repeat delay (250-600 ms), then a repeat every 30-40 ms. The release is then inferred from a gap of
# HOLD_GAP_REPEATS measured repeat intervals, never shorter than HOLD_GAP_MIN_S (terminal input jitter) and
# never longer than HOLD_RELEASE_S (the UR's RTDE watchdog period). Before the first repeat of a hold the
# window is the terminal's repeat delay as measured on earlier holds (HOLD_FIRST_S until one was measured), so
# the first press never stop-starts the arm (a "delay" under HOLD_DELAY_MIN_S is a hold resumed mid-repeat,
# never learned). Key times are when the terminal input thread parsed the key (``key_arrivals``,
# station.tui.keys.KeyArrivals), not when the busy UI got round to it. The UI checks for a release every
# HOLD_CHECK_S and re-commands the motion every HOLD_TICK_S; every position target ends where the arm would be
# shortly after the deadline, so a stalled UI stops it there too (HOLD_WATCHDOG_S: standstill after the last
# key event).
HOLD_RELEASE_S = 0.1
HOLD_GAP_REPEATS = 2.5
HOLD_GAP_MIN_S = 0.05
HOLD_TICK_S = 0.05
HOLD_CHECK_S = 0.01
HOLD_WATCHDOG_S = 0.3
HOLD_FIRST_S = 0.6
RELEASE_LOCK_S = 0.2  # s: a release waits at most this for a re-command in flight, then stops regardless
HOLD_DELAY_MIN_S = 0.15  # s: no terminal's repeat delay is shorter


@dataclass
class Readout:
    q: np.ndarray  # SI
    tcp: np.ndarray  # (6,) x, y, z (m), rx, ry, rz (rad) of the nominal model: roll-pitch-yaw, or UR's rotation vector
    touch: bool | None
    moving: bool
    enabled: bool
    t: float


@dataclass
class SolveState:
    status: str = "waiting"  # waiting | ok | error
    message: str = "no samples yet"
    n_samples: int = 0
    residuals: dict = field(default_factory=dict)
    identified: list[tuple[str, float, float | None, str]] = field(default_factory=list)  # name, value, std, unit
    unidentifiable: dict[str, str] = field(default_factory=dict)
    result: object | None = None  # CalibrationResult
    seconds: float = 0.0


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

    def __init__(self, robot, session: JogSession, *, model: Model | None = None, identify: str = "offsets,tcp",
                 reference: str | dict = "unknown", cell: Cell | None = None, limits: dict | None = None,
                 limits_version: str | None = None, judged_as: str = "jog") -> None:
        self.robot = robot
        self.model: Model = model if model is not None else robot.model
        self.session = session
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
        self.hold_state: dict | None = None
        self.repeat_intervals: deque[float] = deque(maxlen=16)  # the terminal's autorepeat, measured (s)
        self.repeat_delay: float | None = None  # the terminal's delay before the first repeat, measured (s)
        self.release_events = False  # the terminal reported a key release (kitty keyboard protocol)
        # (axis, direction, count) -> (arrivals so far, times of those after count) of that jog key as the
        # terminal's input thread saw them (set by the app; None: key times are the calls' ``now``)
        self.key_arrivals = None
        self._arrival_mark: dict[tuple[int, int], int] = {}  # arrivals already taken by an ended hold
        self._idle_kick = 0.0
        self.predicted: dict[str, float | None] = {}
        self.guide: gd.Guidance = gd.guidance(self.model, self._guide_labels(), [], None, self.limits, None)
        self.verdict: dict | None = None
        self.ur_rotvec = isinstance(robot, CalibrationExport)  # UR pendant shows the rotation vector
        # hold-to-run re-targets position moves, except on a robot with a velocity jog (UR: speedJ/speedL
        # under its RTDE watchdog), where re-targeting moveJ would re-plan and brake on every command
        # (measured 8 of 25 mm/s, 0.5 s late stop): there each tick re-sends the speed instead
        self.velocity_jog = isinstance(robot, VelocityJog)
        self.hold_supported = True
        self.selected: int | None = None  # index into session.samples; None = the latest
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

    def next_point(self, delta: int = 1) -> None:
        self.point_index = (self.point_index + delta) % len(self.labels)
        self.message = f"reference point {self.point}"

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
        """Always available: no lock, no precondition."""
        self._end_hold()
        try:
            self.robot.stop()
            if not quiet:
                self.message = "STOPPED"
        except StationError as e:
            if not quiet:
                self._on_error(e, "stop")

    def poll(self, block: bool = False) -> Readout | None:
        """Refresh joints, TCP, touch and status. Skips (returns None) while another thread talks to the robot
        unless ``block``."""
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
        T = self.model.fk(snap.q)
        rot = se3.matrix_to_rotvec(T[:3, :3]) if self.ur_rotvec else se3.matrix_to_rpy(T[:3, :3])
        tcp = np.concatenate([T[:3, 3], rot])
        self.readout = Readout(np.asarray(snap.q, float), tcp, touch, status.moving, status.enabled, snap.t)
        return self.readout

    def _refuse_axis(self, axis: int) -> str | None:
        if self.fault:
            return "clear the fault first (c)"
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
        if self._checker is None:  # built once: the envelope compile is the expensive part
            if getattr(self.model, "kind", "serial") == "parallel":
                return target  # a parallel model has no link capsules (as in the planner): joint limits only
            self._checker = Checker(self.model, self.keep_out)
        hit = self._checker.path_hit(q0, target)
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

    # ---- hold-to-run -------------------------------------------------------------------------------
    def hold(self, axis: int, direction: int, now: float | None = None) -> bool:
        """A jog key event in hold-to-run mode (the press or one of the terminal's repeats): keep moving
        ``axis`` while events keep coming; :meth:`hold_tick` stops the robot once they stop."""
        refusal = self._refuse_axis(axis)
        if refusal:
            self.message = refusal
            return False
        now = time.monotonic() if now is None else now
        d = 1 if direction > 0 else -1
        h = self.hold_state
        if h is not None and h["axis"] == axis and h["dir"] == d and h["mode"] == self.mode:
            if not self._arrivals_seen(h):
                self._repeat_seen(h, now)
            return True
        seen, times = self._arrivals(axis, d, self._arrival_mark.get((axis, d), 0))
        # the press as the terminal delivered it: the first arrival of this key after the last hold, unless
        # older than a repeat delay (step presses before hold-to-run was chosen, or a UI stalled that long)
        times = [t for t in times if t >= now - HOLD_FIRST_S]
        if seen and not times:
            # a repeat that arrived before the held key's release (or the inferred one) and waited in the UI's
            # queue: the key is no longer held, so it must not start the arm again
            return False
        if h is not None:
            self.stop_hold(quiet=True)
        self.axis = axis
        t0 = times[0] if times else now
        self.hold_state = h = {"axis": axis, "dir": d, "mode": self.mode, "frame": self.frame, "events": 1,
                               "deadline": t0 + self.first_window(), "started": t0, "last": t0, "sent": None,
                               "seen": seen - len(times) + 1 if times else seen}
        self._arrivals_seen(h)  # repeats that arrived while the press waited in the UI's queue
        return self._hold_command(now)

    def _end_hold(self) -> None:
        h, self.hold_state = self.hold_state, None
        if h is not None:  # the key's arrivals so far belong to the ended hold; the next press comes after them
            self._arrival_mark[(h["axis"], h["dir"])] = self._arrivals(h["axis"], h["dir"], 0)[0]

    def _arrivals(self, axis: int, d: int, count: int) -> tuple[int, list[float]]:
        if self.key_arrivals is None:
            return 0, []
        return self.key_arrivals(axis, d, count)

    def _arrivals_seen(self, h: dict) -> bool:
        """Take the held key's repeats the input thread saw since the last look (their own times). False when
        there are no arrival times (no terminal input thread: the caller's ``now`` counts)."""
        seen, times = self._arrivals(h["axis"], h["dir"], h["seen"])
        if not seen:
            return False
        h["seen"] = seen
        for t in times:
            self._repeat_seen(h, max(t, h["last"]))
        return True

    def _repeat_seen(self, h: dict, now: float) -> None:
        """A repeat of the held key: measure the terminal's cadence and move the release deadline."""
        dt = now - h["last"]
        if h["events"] == 1:
            h["delay"] = dt  # the repeat delay (or a second press: confirmed by the cadence that follows)
        else:
            self.repeat_intervals.append(dt)
            if h["events"] == 2 and dt < 0.6 * h["delay"] and h["delay"] >= HOLD_DELAY_MIN_S:
                self.repeat_delay = h["delay"]
        h["events"] += 1
        h["last"] = now
        h["deadline"] = now + self.release_gap()

    def release_gap(self) -> float:
        """Key-event gap taken as a release: HOLD_GAP_REPEATS measured repeat intervals (mean of the last
        16), within [HOLD_GAP_MIN_S, HOLD_RELEASE_S]; HOLD_RELEASE_S until the cadence was measured, and in a
        terminal that reports releases (a lost release still stops within the watchdog period)."""
        if not self.repeat_intervals or self.release_events:
            return HOLD_RELEASE_S  # (the terminal reports releases: the gap is only the backup)
        # the mean, not the median: a busy UI receives repeats in bunches (intervals near 0 then one long),
        # whose median would shrink the gap below the real cadence
        est = statistics.fmean(self.repeat_intervals)
        return float(min(HOLD_RELEASE_S, max(HOLD_GAP_MIN_S, HOLD_GAP_REPEATS * est)))

    def first_window(self) -> float:
        """How long a press keeps the arm moving before its first repeat: the measured repeat delay plus a
        quarter (input jitter), at most HOLD_FIRST_S; HOLD_FIRST_S until a delay was measured."""
        if self.repeat_delay is None:
            return HOLD_FIRST_S
        return float(min(HOLD_FIRST_S, self.repeat_delay + max(HOLD_GAP_MIN_S, 0.25 * self.repeat_delay)))

    def release(self, axis: int, direction: int) -> None:
        """The terminal reported the release of a jog key (kitty keyboard protocol): stop now if it is the
        held one. Safe from the terminal's input thread (the app calls it there, ahead of the UI's queue): a
        re-command in flight is waited for (``io_lock``, at most RELEASE_LOCK_S) and none starts after the hold
        ended (``_hold_command`` re-checks under the lock). If the lock does not come free, a velocity jog is
        stopped anyway (``stop()`` bypasses the lock, as the STOP key does); a position-controlled robot (bus
        not thread-safe) is left to the same release on the UI thread, its targets end near the deadline."""
        self.release_events = True
        d = 1 if direction > 0 else -1
        locked = self.io_lock.acquire(timeout=RELEASE_LOCK_S)
        try:
            # every press/repeat of this key so far belongs to before the release: one still queued for the UI
            # (this runs ahead of the queue) is stale and must not start the arm after the key came up
            self._arrival_mark[(axis, d)] = self._arrivals(axis, d, 0)[0]
            h = self.hold_state
            if h is None or h["axis"] != axis or h["dir"] != d or not (locked or self.velocity_jog):
                return
            self._end_hold()
            self.stop(quiet=True)
            self.message = "key released: stopped"
        finally:
            if locked:
                self.io_lock.release()

    def hold_check(self, now: float | None = None) -> bool:
        """Stop once the release deadline passed (cheap: the UI calls it every HOLD_CHECK_S). True if it stopped."""
        h = self.hold_state
        if h is None:
            return False
        now = time.monotonic() if now is None else now
        if now >= h["deadline"]:
            self._arrivals_seen(h)  # a repeat may wait in the UI's queue: the key is still held
            if now < h["deadline"]:
                return False
            self.stop_hold()
            return True
        return False

    def hold_tick(self, now: float | None = None) -> None:
        """Called by the UI every HOLD_CHECK_S: stop once the key events stopped, else re-command the held
        motion every HOLD_TICK_S."""
        now = time.monotonic() if now is None else now
        if self.hold_check(now):
            return
        h = self.hold_state
        if h is None or (h["sent"] is not None and now - h["sent"] < HOLD_TICK_S * 0.9):
            return
        self._hold_command(now)

    def hold_idle(self, now: float | None = None) -> None:
        """Called by the UI between holds: a velocity-jog robot's watchdog stays armed after a release (UR:
        the RTDE watchdog lives as long as the control script), so keep feeding it every HOLD_TICK_S; else the
        controller ends the program a watchdog period after each release and the next press waits for the
        script to be uploaded again. If the UI stalls anyway, the next press restarts it (slower, still safe)."""
        keep = getattr(self.robot, "jog_keep_alive", None) if self.velocity_jog and not self.fault else None
        now = time.monotonic() if now is None else now
        if keep is None or now - self._idle_kick < HOLD_TICK_S or not self.io_lock.acquire(blocking=False):
            return
        try:
            self._idle_kick = now
            keep()
        except StationError as e:
            self._on_error(e, "jog watchdog")
        finally:
            self.io_lock.release()

    def stop_hold(self, quiet: bool = False) -> None:
        if self.hold_state is None:
            return
        self.stop(quiet=True)
        if not quiet:
            self.message = "key released: stopped"

    def _hold_command(self, now: float) -> bool:
        """Command a target no farther than the robot travels at the override until the deadline: if the UI
        stalls, the robot still stops there by itself."""
        h = self.hold_state
        if h is None:
            return False
        h["sent"] = now
        # the target is where the arm would be two ticks after the deadline (a target much closer makes the
        # drives' profiles brake between commands): a stalled UI still stops the arm there
        horizon = max(h["deadline"] - now, 0.0) + 2 * HOLD_TICK_S
        axis, d = h["axis"], h["dir"]
        cap = self.speed_mm_s * 1e-3
        rotational = self.axis_unit(axis) == "deg"
        rate = self.joint_rate(axis)
        with self.io_lock:
            if self.hold_state is not h:  # released (from the input thread) while this waited for the lock
                return False
            try:
                q0 = np.asarray(self.robot.joint_positions().q, dtype=float)
                if self.velocity_jog:
                    sent = self._hold_velocity(axis, d, q0, cap, rate)
                else:
                    step = d * (rate if rotational or self.mode == "joint" else cap) * horizon
                    target = self.target(q0, axis, step)
                    speed = joint_speed_for_tool_cap(self.model, q0, target, self.lead_rate(axis, q0, target, step),
                                                     cap=cap)
                    lead = float(np.max(np.abs(target - q0)))
                    if lead > speed * horizon > 0:  # slower than asked (tool cap): shorten to the reachable part
                        step *= speed * horizon / lead
                        target = self.target(q0, axis, step)
                    self.robot.move_joints(target, speed=speed, wait=False)
                    sent = {"step": step, "speed": speed, "target": target}
            except LimitError as e:
                self.stop(quiet=True)
                self.message = f"refused: {e}"
                return False
            except StationError as e:
                self._end_hold()
                self._on_error(e, f"jog {self.axis_names()[axis]}")
                return False
        self.last_jog = {"mode": self.mode, "frame": self.frame, "axis": axis, "q0": q0, "cap_m_s": cap,
                         "hold": True, **sent}
        self.message = (f"hold-to-run {self.axis_names()[axis]} {'+' if d > 0 else '-'} at {self.speed_percent} % "
                        f"({self.speed_mm_s:g} mm/s)")
        return True

    def _hold_velocity(self, axis: int, d: int, q0: np.ndarray, cap: float, rate: float) -> dict:
        """Velocity hold (caller holds io_lock and handles errors): re-send the speed each tick; the driver's
        watchdog stops the arm if the ticks stop. Joint speed is limited so the tool stays within the override."""
        if self.mode == "joint":
            probe = self.target(q0, axis, d * 1e-3)  # direction of motion, for the tool-speed bound
            speed = joint_speed_for_tool_cap(self.model, q0, probe, rate, cap=cap)
        elif self.axis_unit(axis) == "deg":
            self.target(q0, axis, d * 1e-3)  # reachable and clear of the keep-out (LimitError otherwise)
            speed = rate  # rad/s about the TCP: the override's share of 30 deg/s
        else:
            speed = cap
        self.robot.jog_velocity(self.mode, axis, d * speed, self.frame)
        return {"velocity": d * speed}

    def enable(self) -> None:
        """Reset a fault: re-enable the robot and clear the banner only if the robot then reports OK."""
        with self.io_lock:
            try:
                self.robot.enable()
                status = self.robot.status()
            except StationError as e:
                self.fault = f"enable: {e}"
                return
        if status.ok:
            self.fault = None
            self.message = "enabled"
            self.session.event(ev.Step(name="enable", status="done"))
        else:
            self.fault = "still faulted: " + "; ".join(status.faults or ("stop input active",))

    # ---- samples ---------------------------------------------------------------------------------------
    def _selected_sample(self) -> ev.Sample | None:
        samples = self.session.samples
        if not samples:
            return None
        i = len(samples) - 1 if self.selected is None else max(0, min(len(samples) - 1, self.selected))
        return samples[i]

    def select(self, delta: int) -> None:
        n = len(self.session.samples)
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
        sample = self.session.add_sample(
            snap.q, point or self.point, raw=snap.raw, raw_unit=snap.raw_unit, t=snap.t, t_device=snap.t_device,
            touch=touch, status={"enabled": status.enabled, "forced": bool(force and touch is False)})
        self.numbers[sample.seq] = len(self.numbers) + 1
        self.selected = None
        self.message = f"recorded #{self.number(sample)} on {sample.point} ({len(self.session.samples)} samples)"
        self.solve()
        if self.guided and self.guide.next_point in self.labels and point is None:
            self.point_index = self.labels.index(self.guide.next_point)  # suggest the next point to touch
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
        samples = self.session.samples
        self.predicted = {}
        if not samples:
            self.solve_state = SolveState()
            self._update_guidance()
            return self.solve_state
        from station.solver import Observations, solve

        q = np.array([s.q for s in samples])
        labels = np.array([s.point for s in samples], dtype=object)
        t0 = time.perf_counter()
        try:
            result = solve(self.model, Observations(q, labels), identify=self.identify, reference=self.reference)
        except (ValueError, KeyError, StationError, np.linalg.LinAlgError) as e:
            self.solve_state = SolveState("error", str(e), len(samples), seconds=time.perf_counter() - t0)
            self._update_guidance()
            return self.solve_state
        dt = time.perf_counter() - t0
        identified = [(n, p.value - p.nominal if p.kind == "model" else p.value, p.std, p.unit)
                      for n, p in result.parameters.items() if p.identifiable]
        self.solve_state = SolveState("ok", "converged" if result.converged else "did not converge", len(samples),
                                      dict(result.residuals), identified, dict(result.unidentifiable), result, dt)
        if self.limits:
            try:
                self.predicted = gd.predicted_std(self.model, q, labels, self.identify, self.reference)
            except (ValueError, KeyError, np.linalg.LinAlgError):
                self.predicted = {}
        self._update_guidance()
        return self.solve_state

    def _update_guidance(self) -> None:
        self.guide = gd.guidance(self.model, self._guide_labels(), self.session.samples, self.solve_state.result,
                                 self.limits, self.predicted)

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
                      session=self.session.session_id, tolerance=self._tolerance, note=note)
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
            measured = gd.measurements(self.model, result, len(self.session.samples), self.predicted)
            self.verdict = gd.judge(self.limits, measured, self.limits_version)
            self.session.event(ev.Verdict(**self.verdict))
            passed = self.verdict["passed"]
        finally:
            self.session.close(passed=passed)

    @property
    def verdict_text(self) -> str:
        """PASS / FAIL / NO LIMITS of the closed session ("" before)."""
        if self.verdict is None:
            return ""
        return self.verdict.get("status") or ("PASS" if self.verdict["passed"] else "FAIL")
