"""The jog UI's logic, apart from any widget: step presets, speed override, jogging through the shared
motion helpers, the touch indicator, record/retake/discard into the session, the live solve, faults and
write-back. Textual widgets only render this state and call these methods (and tests can too)."""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from station.engine import events as ev
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
from station.robot.capabilities import CalibrationStore, ContactSensor
from station.robot.errors import LimitError, StationError
from station.robot.motion import MANUAL_TOOL_SPEED_CAP, jog_target, joint_speed_for_tool_cap
from station.tui.session import JogSession

STEP_PRESETS = (0.01, 0.1, 1.0)  # mm for translations / prismatic joints, deg for rotations
SPEED_PRESETS_MM_S = (5.0, 10.0, 25.0, 50.0, 100.0, 250.0)  # speed override at the tool
POINT_LABELS = tuple("ABCDEFGH")
CART_AXES = ("X", "Y", "Z", "Rx", "Ry", "Rz")
JOG_MAX_JOINT_SPEED = np.deg2rad(30.0)  # rad/s (m/s prismatic): manual jog never faster than this per joint


@dataclass
class Readout:
    q: np.ndarray  # SI
    tcp: np.ndarray  # (6,) x, y, z (m), rx, ry, rz (rad, fixed-axis roll-pitch-yaw) of the nominal model
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
                 reference: str | dict = "unknown") -> None:
        self.robot = robot
        self.model: Model = model if model is not None else robot.model
        self.session = session
        self.identify = identify
        self.reference = reference
        self.io_lock = threading.RLock()
        self.mode = "joint"  # joint | cartesian
        self.axis = 0  # last axis jogged / selected
        self.step_index = 1
        self.speed_index = 2
        self.point_index = 0
        self.selected: int | None = None  # index into session.samples; None = the latest
        self.fault: str | None = None
        self.message = "ready"
        self.readout: Readout | None = None
        self.stale = False  # the last poll failed: the readout shows the last known values
        self.solve_state = SolveState()
        self.writeback_done: dict | None = None
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
    def speed_mm_s(self) -> float:
        return min(SPEED_PRESETS_MM_S[self.speed_index], MANUAL_TOOL_SPEED_CAP * 1e3)

    @property
    def point(self) -> str:
        return POINT_LABELS[self.point_index]

    def set_step(self, index: int) -> None:
        self.step_index = max(0, min(len(STEP_PRESETS) - 1, index))
        self.message = f"step {self.step:g} mm / deg"

    def change_speed(self, delta: int) -> None:
        self.speed_index = max(0, min(len(SPEED_PRESETS_MM_S) - 1, self.speed_index + delta))
        self.message = f"speed override {self.speed_mm_s:g} mm/s at the tool"

    def toggle_mode(self) -> None:
        self.mode = "cartesian" if self.mode == "joint" else "joint"
        self.message = f"{self.mode} jog"

    def next_point(self, delta: int = 1) -> None:
        self.point_index = (self.point_index + delta) % len(POINT_LABELS)
        self.message = f"reference point {self.point}"

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
        tcp = np.concatenate([T[:3, 3], se3.matrix_to_rpy(T[:3, :3])])
        self.readout = Readout(np.asarray(snap.q, float), tcp, touch, status.moving, status.enabled, snap.t)
        return self.readout

    def jog(self, axis: int, direction: int) -> bool:
        """One step of the current preset on ``axis`` (joint index or 0..5 = X Y Z Rx Ry Rz), sign from
        ``direction``. Target and speed come from the shared motion helpers; the move is started without
        waiting (``move_joints(wait=False)``), so the UI thread stays free for STOP and every bus transaction
        stays on one thread (the Dynamixel SDK port is not thread-safe)."""
        if self.fault:
            self.message = "clear the fault first (c)"
            return False
        if self.mode == "joint" and axis >= self.model.n_joints:
            self.message = f"this robot has {self.model.n_joints} joints"
            return False
        if self.mode == "cartesian" and axis >= 3 and self.model.n_joints < 6:
            # jog_target solves position only below 6 joints: a rotation step would silently do nothing
            self.message = f"a {self.model.n_joints}-joint arm jogs its tool position only: use joint mode to turn it"
            return False
        self.axis = axis
        step = float(np.sign(direction)) * self.step_si(axis)
        cap = self.speed_mm_s * 1e-3
        with self.io_lock:
            try:
                status = self.robot.status()
                if status.moving:
                    self.message = "still moving: wait, or STOP (space)"
                    return False
                q0 = np.asarray(self.robot.joint_positions().q, dtype=float)
                target = jog_target(self.model, q0, self.mode, axis, step)  # LimitError: nothing sent
                # lead-joint speed that keeps the tool at or below the override along the whole step; the
                # joint cap keeps wrist rotations (tool point nearly still) from snapping round
                speed = joint_speed_for_tool_cap(self.model, q0, target, JOG_MAX_JOINT_SPEED, cap=cap)
                self.robot.move_joints(target, speed=speed, wait=False)
            except StationError as e:
                self._on_error(e, f"jog {self.axis_names()[axis]}")
                return False
        self.last_jog = {"mode": self.mode, "axis": axis, "step": step, "speed": speed, "q0": q0, "target": target,
                         "cap_m_s": cap}
        self.message = f"jog {self.axis_names()[axis]} {'+' if step > 0 else '-'}{self.step:g} {self.axis_unit(axis)}"
        return True

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
        self.selected = None
        self.message = f"recorded #{sample.seq} on {sample.point} ({len(self.session.samples)} samples)"
        self.solve()
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
        self.message = f"retook #{old.seq} as #{new.seq} on {new.point}"
        self.solve()
        return new

    def discard(self) -> ev.Sample | None:
        old = self._selected_sample()
        if old is None:
            self.message = "nothing to discard"
            return None
        self.session.discard(old, reason="technician")
        self.selected = None
        self.message = f"discarded #{old.seq}"
        self.solve()
        return old

    # ---- live solve ------------------------------------------------------------------------------------
    def solve(self) -> SolveState:
        samples = self.session.samples
        if not samples:
            self.solve_state = SolveState()
            return self.solve_state
        from station.solver import Observations, solve

        q = np.array([s.q for s in samples])
        labels = np.array([s.point for s in samples], dtype=object)
        t0 = time.perf_counter()
        try:
            result = solve(self.model, Observations(q, labels), identify=self.identify, reference=self.reference)
        except (ValueError, KeyError, StationError, np.linalg.LinAlgError) as e:
            self.solve_state = SolveState("error", str(e), len(samples), seconds=time.perf_counter() - t0)
            return self.solve_state
        dt = time.perf_counter() - t0
        identified = [(n, p.value - p.nominal if p.kind == "model" else p.value, p.std, p.unit)
                      for n, p in result.parameters.items() if p.identifiable]
        self.solve_state = SolveState("ok", "converged" if result.converged else "did not converge", len(samples),
                                      dict(result.residuals), identified, dict(result.unidentifiable), result, dt)
        return self.solve_state

    # ---- write-back ------------------------------------------------------------------------------------
    def writeback_plan(self) -> WritebackPlan | None:
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

    def writeback_apply(self, plan: WritebackPlan) -> bool:
        """Only after the technician confirmed ``plan``: the engine's two-phase write-back
        (``station.engine.writeback.apply``: pre-image journaled and backed up, write, read back). A failure
        leaves the restore plan armed. Returns whether the device reads back what was written."""
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
        try:
            result = self.solve_state.result
            if result is not None and self.writeback_done is None:
                self.session.event(ev.Result(result=result.to_dict()))
        finally:
            self.session.close()
