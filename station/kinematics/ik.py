"""Batched numeric inverse kinematics: damped least squares (Levenberg-Marquardt) on the analytic
joint Jacobian, clamped to joint limits. Converges from nearby seeds; give several seeds for far targets."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.kinematics import se3


@dataclass(frozen=True)
class IKResult:
    q: np.ndarray  # (N, n)
    ok: np.ndarray  # (N,) bool: converged within tolerance and inside limits
    position_error: np.ndarray  # (N,) m
    orientation_error: np.ndarray  # (N,) rad (0 when position only)
    iterations: int


def solve_ik(model, target, q0, *, params=None, position_only: bool | None = None, tol_pos: float = 1e-7,
             tol_rot: float = 1e-7, max_iter: int = 200, damping: float = 1e-3,
             weights: np.ndarray | None = None) -> IKResult:
    """``target`` is ``(N,3)`` positions or ``(N,4,4)`` poses (also unbatched). ``q0`` ``(N,n)`` or ``(n,)``.

    ``weights`` (n,) scales how willingly each joint moves (minimum-norm in weighted joint space), so
    a redundant position-only solve stays close to ``q0``."""
    target = np.asarray(target, dtype=float)
    pose = target.shape[-2:] == (4, 4)
    if position_only is None:
        position_only = not pose
    tgt = target.reshape((-1, 4, 4) if pose else (-1, 3))
    N = tgt.shape[0]
    q = np.array(np.broadcast_to(np.atleast_2d(q0), (N, model.n_joints)), dtype=float)
    lo, hi = model.lower, model.upper
    W = np.ones(model.n_joints) if weights is None else np.asarray(weights, dtype=float)
    p_t = tgt[:, :3, 3] if pose else tgt
    lam = np.full(N, damping)
    it = 0
    fast = getattr(model, "fk_and_jacobian_q", None)  # serial models: no parameter Jacobian to build
    for it in range(1, max_iter + 1):  # noqa: B007
        T, Jq = fast(q, params) if fast is not None else model.jacobians(q, params)[:2]
        e = p_t - T[:, :3, 3]
        J = Jq[:, :3]
        if not position_only:
            e = np.concatenate([e, se3.orientation_error(tgt[:, :3, :3], T[:, :3, :3])], axis=1)
            J = Jq
        err_p = np.linalg.norm(e[:, :3], axis=1)
        err_r = np.zeros(N) if position_only else np.linalg.norm(e[:, 3:], axis=1)
        done = (err_p < tol_pos) & (err_r < tol_rot)
        if done.all():
            break
        JW = J * W[None, None, :]
        A = JW @ np.swapaxes(JW, 1, 2) + (lam[:, None, None] ** 2) * np.eye(J.shape[1])
        dq = W[None, :] * np.einsum("nji,nj->ni", JW, np.linalg.solve(A, e[..., None])[..., 0])
        step = np.linalg.norm(dq, axis=1)
        scale = np.minimum(1.0, 0.5 / np.maximum(step, 1e-12))  # at most 0.5 rad per iteration
        q_new = np.where(done[:, None], q, np.clip(q + dq * scale[:, None], lo, hi))
        q = q_new
    T = model.fk(q, params).reshape(-1, 4, 4)
    err_p = np.linalg.norm(p_t - T[:, :3, 3], axis=1)
    err_r = (np.zeros(N) if position_only else
             np.linalg.norm(se3.orientation_error(tgt[:, :3, :3], T[:, :3, :3]), axis=1))
    ok = (err_p < max(tol_pos, 1e-6)) & (err_r < max(tol_rot, 1e-5)) & model.within_limits(q)
    return IKResult(q, ok, err_p, err_r, it)
