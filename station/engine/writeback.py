"""The one write-back of joint zero offsets, used by ``station run --apply`` and the jog UI alike
(docs/architecture.md, write-back semantics; journal phases in ``station.engine.events.Writeback``).

Two phases, each journaled before the next begins:
1. pre-image: what the device holds now and what will be written are journaled, and the session's first
   pre-image is kept in ``calibration-backup.json`` (written atomically, fsynced) before anything is written;
2. write (the driver stores persistently), read back, compare to one encoder count: ``written`` or ``failed``.
The engine then verifies with a touch at a known pose (``verified``).

A transaction: SIGINT/SIGTERM are held off from the pre-image to the read-back (:func:`signals_held`) and acted
on right after, so Ctrl-C never leaves half a calibration. What a signal cannot hold off (kill -9, power loss, a
drive reboot) is found again by :func:`resume_point`: the device holds the pre-image (write again), the new
values (the write is sent again, so a device's own store command is re-sent, then go on with the check), a mix of
both per joint (a write cut in the middle: written again in full), or anything else (refused: a person must look;
``station restore SESSION`` writes the backup). The jog UI and ``station restore`` restore with the same
:func:`apply` (``kind="restore"``)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.engine.events import Writeback
from station.robot.capabilities import CalibrationExport, CalibrationStore, WritePose
from station.robot.errors import DeviceFault, StationError
from station.safeio import loads_strict

BACKUP = "calibration-backup.json"
BACKUP_FORMAT = "station-calibration-backup/1"
FLOAT_TOL = 1e-9  # rad/m on top of the device resolution
MAX_POSE_MOVES = 40  # moves a WritePose robot may ask for before a write


class WriteBackError(DeviceFault):
    pass


@dataclass
class WritebackPlan:
    """What a write-back will do, before it does it (the jog UI shows it for confirmation)."""

    before: dict[str, float]  # what the device holds now (SI)
    after: dict[str, float]  # what will be written (SI)
    corrections: dict[str, float] = field(default_factory=dict)  # identified offsets (empty for a restore)
    kind: str = "write"  # "write" | "restore" (back to the pre-image after a failed write-back)


def corrections_of(result) -> dict[str, float]:
    """The identified joint zero offsets of a ``CalibrationResult`` relative to the model in use (SI)."""
    return {n: float(p.value - p.nominal) for n, p in result.parameters.items()
            if n.startswith("offset.") and p.identifiable}


def plan_write(before: dict[str, float], corrections: dict[str, float]) -> WritebackPlan:
    """``after = before + correction`` for every joint the device calibrates (so that the identified offsets are
    ~0 on the next verify)."""
    before = {k: float(v) for k, v in before.items()}
    after = {k: before[k] + corrections.get(k, 0.0) for k in before}
    return WritebackPlan(before, after, dict(corrections))


def plan_restore(now: dict[str, float], pre_image: dict[str, float]) -> WritebackPlan:
    return WritebackPlan({k: float(v) for k, v in now.items()}, dict(pre_image), {}, "restore")


def count_tolerance(model, name: str, counts: float = 1.0) -> float:
    """``counts`` encoder counts of the joint behind ``offset.jN`` in SI (what a device can store), plus float
    rounding; joints without device scaling: the rounding only."""
    try:
        enc = model.joints[int(name.rsplit("j", 1)[1]) - 1].encoder
    except (ValueError, IndexError):
        enc = None
    if enc is None:
        return FLOAT_TOL
    return counts / (enc.counts_per_unit * enc.gear) + FLOAT_TOL


def _mismatch(have: dict, want: dict, tol: Callable[[str], float]) -> str | None:
    return next((k for k in want if abs(have.get(k, math.nan) - want[k]) > tol(k)), None)


def matches(have: dict, want: dict, tol: Callable[[str], float]) -> bool:
    return _mismatch(have, want, tol) is None


def read_device(robot) -> dict[str, float]:
    return {k: float(v) for k, v in (robot.read_calibration() or {}).items()}


def write_backup(folder: Path, session: str, plan: WritebackPlan) -> Path:
    """Keep the session's first pre-image (the one to restore to) in ``calibration-backup.json``; an existing
    backup is never overwritten. Atomic and fsynced before the device is touched."""
    path = Path(folder) / BACKUP
    if path.exists():
        return path
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w") as f:
        json.dump({"format": BACKUP_FORMAT, "units": "SI (m, rad)", "session": session, "t": time.time(),
                   "before": plan.before, "after": plan.after}, f, indent=2)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


@contextlib.contextmanager
def signals_held():
    """SIGINT and SIGTERM are noted, not acted on, inside the block; the first one noted is delivered again
    (to the handler in place before) when the block ends. Only the main thread can hold signals; elsewhere the
    block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def note(signum, frame):
        pending.append(signum)

    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(ValueError, OSError):
            old[sig] = signal.signal(sig, note)
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if pending:
            signal.raise_signal(pending[0])  # acted on now, by the handler the caller had


def apply(robot, plan: WritebackPlan, *, event: Callable[[Writeback], object], folder: Path, session: str,
          tolerance: Callable[[str], float], note: str = "", resumed: bool = False) -> dict[str, float]:
    """Write ``plan.after`` into the device as phase 1 (pre-image journaled and backed up) and phase 2 (write,
    read back within ``tolerance``); returns the read-back. A bus error or a read-back that differs journals
    ``failed`` and raises (``WriteBackError`` for the read-back). ``resumed``: the pre-image of this plan is
    journaled already (an interrupted write-back being finished). SIGINT/SIGTERM wait until it returns."""
    with signals_held():
        return _apply(robot, plan, event=event, folder=folder, session=session, tolerance=tolerance, note=note,
                      resumed=resumed)


def _apply(robot, plan: WritebackPlan, *, event, folder, session, tolerance, note, resumed) -> dict[str, float]:
    if not resumed:
        backup = None if plan.kind == "restore" else str(write_backup(folder, session, plan))
        event(Writeback(phase="pre-image", kind=plan.kind, before=plan.before, after=plan.after, backup=backup,
                        note=note))
    try:
        robot.write_calibration(plan.after)
        readback = read_device(robot)
    except StationError as e:
        event(Writeback(phase="failed", kind=plan.kind, before=plan.before, after=plan.after, error=str(e),
                        note=note))
        raise
    bad = _mismatch(readback, plan.after, tolerance)
    if bad is not None:
        msg = f"write-back: {bad} reads back {readback.get(bad)!r}, wrote {plan.after[bad]!r}"
        event(Writeback(phase="failed", kind=plan.kind, before=plan.before, after=plan.after, readback=readback,
                        error=msg, note=note))
        raise WriteBackError(msg)
    event(Writeback(phase="written", kind=plan.kind, before=plan.before, after=plan.after, readback=readback,
                    applied=True, note=note))
    return readback


def resume_point(events: list, device: dict[str, float], tol: Callable[[str], float]):
    """Where an interrupted write-back stands: ``(None, None)`` when none was started, else ``(plan, state)``
    with ``state`` "written" (the device holds the new values), "pre-image" (it holds the old ones) or
    "unknown"."""
    pre = [e for e in events if isinstance(e, Writeback) and e.phase == "pre-image" and e.kind == "write"]
    if not pre:
        return None, None
    plan = WritebackPlan(dict(pre[-1].before or {}), dict(pre[-1].after or {}))
    if matches(device, plan.after, tol):
        return plan, "written"
    if matches(device, plan.before, tol):
        return plan, "pre-image"
    if all(abs(device.get(k, math.nan) - plan.after[k]) <= tol(k)
           or abs(device.get(k, math.nan) - plan.before.get(k, math.nan)) <= tol(k) for k in plan.after):
        return plan, "partial"  # every joint holds its old or its new value: a write cut in the middle
    return plan, "unknown"


def finished_writes(events: list) -> bool:
    """The last write-back attempt was journaled ``written`` (nothing left to finish but the check)."""
    last = None
    for e in events:
        if isinstance(e, Writeback) and e.kind == "write" and e.phase in ("pre-image", "written", "failed"):
            last = e.phase
    return last == "written"


def load_backup(folder: Path) -> dict:
    """The session's ``calibration-backup.json`` (its first pre-image, SI); one line when missing/damaged."""
    path = Path(folder) / BACKUP
    try:
        doc = loads_strict(path.read_text(), str(path))
    except FileNotFoundError:
        raise StationError(f"{path}: no backup (this session never started a write-back)") from None
    except (OSError, ValueError) as e:
        raise StationError(f"{path}: unreadable backup ({e})") from None
    before = doc.get("before") if isinstance(doc, dict) else None
    if doc.get("format") != BACKUP_FORMAT or not isinstance(before, dict) or not before or not all(
            isinstance(v, (int, float)) and math.isfinite(v) for v in before.values()):
        raise StationError(f"{path}: not a {BACKUP_FORMAT} file with finite 'before' values")
    return doc


def restore(robot, folder: Path, session: str, *, event: Callable[[Writeback], object],
            tolerance: Callable[[str], float], note: str = "") -> dict[str, float]:
    """Write the session's backup (its first pre-image) back into the device as a transaction
    (``kind="restore"``): journaled, signals held, read back. Returns the read-back."""
    pre = {k: float(v) for k, v in load_backup(folder)["before"].items()}
    plan = plan_restore(read_device(robot), pre)
    return apply(robot, plan, event=event, folder=folder, session=session, tolerance=tolerance,
                 note=note or f"restored from {BACKUP}")


# ---- the engine's step ------------------------------------------------------------------------------------
def write_back(s, check_pose=None) -> dict:
    """The engine's write-back step (``s.write_back()`` with ``--apply``): plan from the solve, apply, then
    verify with a touch at a known pose. Returns the session record's write-back summary."""
    res = s.result
    if res is None:
        raise StationError("write-back: nothing solved yet")
    if isinstance(s.robot, CalibrationExport):
        # a controller that keeps its calibration itself (UR): nothing is written to the robot; the driver
        # exports calibration.conf / URDF for the integrator to install
        files = [str(p) for p in s.robot.export_calibration(res, s.folder / "controller-calibration") or []]
        s.event(Writeback(phase="exported", files=files,
                          note="controller keeps its calibration; exported " + ", ".join(files)))
        return s.record_dict()["writeback"]
    if not isinstance(s.robot, CalibrationStore):
        s.event(Writeback(phase="unsupported", note="the robot stores no joint calibration the station can write"))
        return s.record_dict()["writeback"]
    before = s.robot.read_calibration()
    before = {k: float(v) for k, v in (before or {}).items()}
    if not before:
        s.event(Writeback(phase="unsupported", note="the robot exposes no writable joint calibration"))
        return s.record_dict()["writeback"]
    tol = s.readback_tolerance
    plan, state = resume_point(s.events("writeback"), before, s.cal_tolerance)
    if plan is None:
        plan = plan_write(before, corrections_of(res))
        to_write_pose(s, plan.after)
        apply(s.robot, plan, event=s.event, folder=s.folder, session=s.id, tolerance=tol)
    elif state == "pre-image" and not finished_writes(s.events("writeback")):  # cut before the write landed
        to_write_pose(s, plan.after)
        apply(s.robot, plan, event=s.event, folder=s.folder, session=s.id, tolerance=tol, resumed=True,
              note="written on resume")
    elif state == "written" and finished_writes(s.events("writeback")):
        pass  # journaled written before the interruption: go on with the check
    elif state in ("written", "partial"):
        # cut before "written" was journaled: the values may sit in volatile memory only (a CANopen drive
        # before its 0x1010 store) or on some joints only; write them all again so the device's own store
        # command is sent again, and read back
        to_write_pose(s, plan.after)
        apply(s.robot, plan, event=s.event, folder=s.folder, session=s.id, tolerance=tol, resumed=True,
              note=f"finished on resume (device held {'the new values' if state == 'written' else 'a mix'})")
    else:
        raise WriteBackError("write-back: the device calibration is neither the journaled pre-image nor the new "
                             f"values; not touching it (put the backup back with: station restore {s.id})")
    check = verify_known_pose(s, check_pose)
    s.event(Writeback(phase="verified", verified=bool(check["passed"]), check=check))
    return s.record_dict()["writeback"]


def to_write_pose(s, values: dict[str, float]) -> None:
    """A robot that stores its calibration only with a joint's power off (``WritePose``: DYNAMIXEL EEPROM, no
    brake) says where the arm must stand for the write; the arm goes there along the collision-checked route from
    where it stands, as often as the robot asks (it measures at each pose), before anything is written."""
    if not isinstance(s.robot, WritePose):
        return
    from station.engine.plan import route_from

    for _ in range(MAX_POSE_MOVES):
        q = s.robot.write_pose(values)
        if q is None:
            return
        s.check_space("the move to the write-back pose")
        for via in route_from(s.model, s.cell.keep_out if s.cell else None, s.robot.joint_positions().q, [q],
                              what="the write-back pose"):
            s.robot.move_joints(via)
    raise WriteBackError(f"write-back: the robot asked for more than {MAX_POSE_MOVES} moves to reach a pose it can "
                         "be written in; nothing was written")


def verify_known_pose(s, pose=None) -> dict:
    """Seat at a known pose; with the new calibration, the nominal model should put the tip where the solve
    placed the reference (distance judged against the ``writeback_check`` limit, default 3x the fit RMS)."""
    plan = s.current_plan
    pose = pose or (plan.of_set("holdout") or plan.of_set("fit"))[0]
    pts = s.result.points()
    s.approach(pose)
    s.seat(pose)
    q = s.robot.joint_positions().q
    s.leave(pose)
    p = s.model.position(np.asarray(q, float))
    target = pts.get(pose.point)
    if target is None or not np.all(np.isfinite(target)):
        return {"passed": True, "note": f"point {pose.point} position not solved; seating succeeded"}
    dist = float(np.linalg.norm(p - target))
    m = s.measure("writeback_check", dist, "length")
    if "writeback_check" not in s.limits:
        rms = s.result.residuals.get("rms_after_m") or 0.0
        m["high"] = max(3 * rms, 50e-6)
        m["passed"] = dist <= m["high"]
    return {"passed": bool(m["passed"]), "distance_m": dist, "pose": pose.index, "q": list(map(float, q))}
