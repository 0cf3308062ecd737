"""Bus-independent motion helpers every driver uses: limit checks, jog targets, tool-speed caps.

Drivers call these before sending anything, so a refused command never reaches the wire."""

from __future__ import annotations

import numpy as np

from station.kinematics import Model
from station.robot.errors import LimitError

MANUAL_TOOL_SPEED_CAP = 0.25  # m/s at the tool for any manual/jog motion (DEVELOPERS.md safety rule)


def check_joint_limits(model: Model, q: np.ndarray, what: str = "target") -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (model.n_joints,):
        raise LimitError(f"{what}: expected {model.n_joints} joint values, got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise LimitError(f"{what}: joint values must be finite, got {q.tolist()}")
    bad = np.flatnonzero((q < model.lower) | (q > model.upper))
    if bad.size:
        i = int(bad[0])
        j = model.joints[i]
        unit, k = ("deg", 180 / np.pi) if j.revolute else ("mm", 1e3)
        raise LimitError(f"{what}: joint {i + 1} ({j.name}) = {q[i] * k:.3f} {unit} is outside its limits "
                         f"[{j.lower * k:.3f}, {j.upper * k:.3f}] {unit}; nothing was sent")
    return q


def jog_target(model: Model, q: np.ndarray, mode: str, axis: int, step: float) -> np.ndarray:
    """Joint target for one jog step. ``joint``: ``axis`` is a joint index, ``step`` in rad/m.
    ``cartesian``: ``axis`` 0..2 = tool x/y/z translation (m) in the base frame, 3..5 = rotation (rad)
    about base x/y/z through the TCP; solved by IK on the nominal model from ``q``."""
    q = np.asarray(q, dtype=float)
    if mode == "joint":
        if not 0 <= axis < model.n_joints:
            raise LimitError(f"jog: joint axis {axis} does not exist (0..{model.n_joints - 1})")
        target = q.copy()
        target[axis] += step
        return check_joint_limits(model, target, "jog")
    if mode != "cartesian":
        raise LimitError(f"jog: mode must be 'joint' or 'cartesian', got {mode!r}")
    if not 0 <= axis < 6:
        raise LimitError(f"jog: cartesian axis {axis} must be 0..5 (x, y, z, rx, ry, rz)")
    T = model.fk(q)
    goal = T.copy()
    if axis < 3:
        goal[axis, 3] += step
    else:
        from station.kinematics.se3 import rotvec_to_matrix

        rv = np.zeros(3)
        rv[axis - 3] = step
        goal[:3, :3] = rotvec_to_matrix(rv) @ T[:3, :3]
    # keep orientation for translations where the arm has the DOF; otherwise position only
    full = model.n_joints >= 6
    res = model.ik(goal if full else goal[:3, 3], q, position_only=not full or None)
    if not res.ok[0]:
        raise LimitError(f"jog: cartesian step {step:g} on axis {'xyz'[axis % 3]} is not reachable "
                         "within joint limits from here")
    return check_joint_limits(model, res.q[0], "jog")


def joint_speed_for_tool_cap(model: Model, q0: np.ndarray, q1: np.ndarray, requested: float | None,
                             cap: float = MANUAL_TOOL_SPEED_CAP, samples: int = 8) -> float:
    """Largest synchronised joint speed (rad/s, along the straight joint path q0 -> q1, for the joint that
    moves most) that keeps the tool at or below ``cap`` m/s, and not above ``requested`` or joint limits."""
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    dq = q1 - q0
    lead = float(np.max(np.abs(dq)))
    vmax = float(np.min(model.max_velocity[np.abs(dq) > 1e-12])) if lead > 0 else float(model.max_velocity.min())
    speed = vmax if requested is None else min(float(requested), vmax)
    if lead <= 0:
        return speed
    s = np.linspace(0.0, 1.0, samples)[:, None]
    Jq = model.jacobian_q(q0 + s * dq)[:, :3]  # tool linear velocity per joint velocity
    tool_per_lead = np.max(np.linalg.norm(Jq @ (dq / lead), axis=1))  # m/s of tool per rad/s of lead joint
    if tool_per_lead > 1e-12:
        speed = min(speed, cap / tool_per_lead)
    return speed
