"""Closed-form TCP methods (linear least squares, no model needed).

* ``tcp_from_flange_poses``: flange poses ``(R_i, p_i)`` as a controller reports them while the tool tip
  rests on one fixed point ``c``: ``R_i t + p_i = c``; unknowns ``t`` (flange frame) and ``c`` (base).
* ``tcp_scara_4point`` (SCARA): the same with ``R_i = Rz(theta_i)``; per touch the rows
  ``[cos, -sin, 0, -1, 0, 0]``, ``[sin, cos, 0, 0, -1, 0]``, ``[0, 0, 1, 0, 0, -1]`` = ``-(x_i, y_i, z_i)``.
  Rotations about one axis cannot separate the tool length from the point height: ``tcp.z`` needs the
  point's z (``point_z``), otherwise it is reported unidentifiable.
* ``tcp_circle_fit`` (XYZR): flange positions recorded while the R axis turns with the tip on a
  fixed point lie on a circle around that point; plane + circle fit give the centre (the tip) and the
  radius (the tool's offset from the R axis)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.kinematics import se3
from station.solver.observations import SolverInputError

RCOND = 1e-9  # relative singular value below which a direction of the linear system is not determined


@dataclass
class TcpFit:
    tcp: np.ndarray  # (3,) tool offset in the flange frame (m); NaN where not identifiable
    point: np.ndarray  # (3,) fixed point in the base frame (m); NaN where not identifiable
    tcp_std: np.ndarray
    point_std: np.ndarray
    rank: int
    rms_m: float  # per-touch residual RMS (3D)
    max_m: float
    unidentifiable: dict[str, str] = field(default_factory=dict)


@dataclass
class CircleFit:
    centre: np.ndarray  # (3,) m, the fixed tip point
    radius: float  # m, distance of the tool tip from the R axis
    normal: np.ndarray  # (3,) unit normal of the circle plane (the R axis direction)
    rms_m: float  # RMS distance of the points from the fitted circle
    tcp: np.ndarray | None  # (3,) tool offset in the flange frame when the angles were given
    n_points: int


NAMES = ("tcp.x", "tcp.y", "tcp.z", "point.x", "point.y", "point.z")


def _rigid_lsq(R: np.ndarray, p: np.ndarray, known_point_z: float | None = None) -> TcpFit:
    N = len(p)
    A = np.zeros((3 * N, 6))
    A[:, :3] = R.reshape(3 * N, 3)
    A[:, 3:] = -np.tile(np.eye(3), (N, 1))
    b = -p.reshape(-1)
    names = list(NAMES)
    if known_point_z is not None:
        b = b - A[:, 5] * known_point_z
        A, names = A[:, :5], names[:5]
    if not np.isfinite(A).all() or not np.isfinite(b).all():
        raise SolverInputError("tcp: poses contain NaN or infinite values")
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > RCOND * s[0]
    rank = int(keep.sum())
    x = Vt[keep].T @ ((U[:, keep].T @ b) / s[keep])
    # a parameter is determined when it has no component in the null space
    null = Vt[~keep]
    determined = np.all(np.abs(null) < 1e-6, axis=0) if len(null) else np.ones(len(names), bool)
    r = A @ x - b
    dof = 3 * N - rank
    sigma2 = float(r @ r) / dof if dof > 0 else np.nan
    cov = (Vt[keep].T / s[keep] ** 2) @ Vt[keep] * sigma2
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    unid: dict[str, str] = {}
    for i, n in enumerate(names):
        if not determined[i]:
            partners = [names[k] for k in range(len(names)) if k != i and np.any(np.abs(null[:, k]) > 1e-6)]
            unid[n] = (f"confounded with {', '.join(partners)}: the orientations do not span enough rotation "
                       f"axes (add touches with the tool tilted about another axis, or give the point)")
            x[i], std[i] = np.nan, np.nan
    full = np.concatenate([x, [known_point_z]]) if known_point_z is not None else x
    full_std = np.concatenate([std, [0.0]]) if known_point_z is not None else std
    d = np.linalg.norm(r.reshape(-1, 3), axis=1)
    return TcpFit(full[:3], full[3:], full_std[:3], full_std[3:], rank, float(np.sqrt(np.mean(d**2))),
                  float(d.max()), unid)


def tcp_from_flange_poses(poses, rotation: str = "rotvec", point_z: float | None = None) -> TcpFit:
    """``poses`` (N, 6) = x, y, z (m), rx, ry, rz (rotation vector as a UR controller reports it, or
    ``rotation="rpy"``), or (N, 4, 4) flange transforms, all touching one fixed point with the tool tip."""
    P = np.asarray(poses, dtype=float)
    if P.ndim == 2 and P.shape[1] == 6:
        T = se3.pose_to_matrix(P, rotation)
    elif P.ndim == 3 and P.shape[1:] == (4, 4):
        T = P
    else:
        raise SolverInputError(f"tcp_from_flange_poses: expected (N, 6) poses or (N, 4, 4), got {P.shape}")
    if len(T) < 3:
        raise SolverInputError(f"tcp_from_flange_poses: {len(T)} poses; need at least 3 with different orientations")
    return _rigid_lsq(T[:, :3, :3], T[:, :3, 3], point_z)


def tcp_scara_4point(flange_xyz, theta, point_z: float | None = None) -> TcpFit:
    """Seed 001: flange positions ``(N, 3)`` (m) and flange rotation about Z ``theta`` (N,) (rad), N >= 4
    touches of one fixed point. ``tcp.z`` is only determined with the point's height ``point_z``."""
    P = np.asarray(flange_xyz, dtype=float)
    th = np.asarray(theta, dtype=float).reshape(-1)
    if P.ndim != 2 or P.shape[1] != 3 or len(th) != len(P):
        raise SolverInputError(f"tcp_scara_4point: expected (N, 3) positions and (N,) angles, "
                               f"got {P.shape}, {th.shape}")
    if len(P) < 4:
        raise SolverInputError(f"tcp_scara_4point: {len(P)} touches; the 4-point method needs at least 4")
    c, s = np.cos(th), np.sin(th)
    R = np.zeros((len(th), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    fit = _rigid_lsq(R, P, point_z)
    if point_z is None and "tcp.z" in fit.unidentifiable:
        fit.unidentifiable["tcp.z"] = ("all rotations are about Z: the tool length cannot be told from the point "
                                       "height (point.z); give point_z")
        fit.unidentifiable["point.z"] = "all rotations are about Z: confounded with tcp.z"
    return fit


def tcp_circle_fit(points, theta=None) -> CircleFit:
    """Seed 003c: ``points`` (N, 3) flange positions (m) recorded while the R axis turns and the tool tip
    stays on a fixed point. With the R angles ``theta`` (N,) the tool offset in the flange frame is also
    returned (z = the height of the flange above the tip, along the plane normal)."""
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or not np.isfinite(P).all():
        raise SolverInputError(f"tcp_circle_fit: expected finite (N, 3) points, got {P.shape}")
    if len(P) < 3:
        raise SolverInputError(f"tcp_circle_fit: {len(P)} points; a circle needs at least 3")
    c0 = P.mean(axis=0)
    _, s, Vt = np.linalg.svd(P - c0)
    if s[1] < 1e-9 * max(s[0], 1e-300) or s[0] == 0:
        raise SolverInputError("tcp_circle_fit: the points are collinear or identical; rotate the R axis further")
    e1, e2, normal = Vt[0], Vt[1], Vt[2]
    if normal[2] < 0:
        normal, e2 = -normal, -e2
    uv = np.column_stack([(P - c0) @ e1, (P - c0) @ e2])
    # algebraic (Kasa) fit u^2+v^2 = 2a u + 2b v + k, then geometric Gauss-Newton refinement
    A = np.column_stack([2 * uv, np.ones(len(uv))])
    a, b, k = np.linalg.lstsq(A, (uv**2).sum(axis=1), rcond=None)[0]
    ctr = np.array([a, b])
    rad = float(np.sqrt(k + a * a + b * b))
    for _ in range(20):
        d = uv - ctr
        dist = np.linalg.norm(d, axis=1)
        res = dist - rad
        Jc = np.column_stack([-d / dist[:, None], -np.ones(len(d))])
        step = np.linalg.lstsq(Jc, -res, rcond=None)[0]
        ctr, rad = ctr + step[:2], rad + step[2]
        if np.max(np.abs(step)) < 1e-13:
            break
    centre_plane = c0 + ctr[0] * e1 + ctr[1] * e2
    off_plane = (P - c0) @ normal
    dist = np.linalg.norm(uv - ctr, axis=1)
    rms = float(np.sqrt(np.mean((dist - rad) ** 2 + off_plane**2)))
    tcp = None
    if theta is not None:
        th = np.asarray(theta, dtype=float).reshape(-1)
        if len(th) != len(P):
            raise SolverInputError(f"tcp_circle_fit: {len(P)} points but {len(th)} angles")
        # the tip is the circle centre; in the flange frame it is Rz(theta)^T (centre - p) in the plane
        vec = centre_plane - P
        c, s = np.cos(th), np.sin(th)
        tx = c * vec[:, 0] + s * vec[:, 1]
        ty = -s * vec[:, 0] + c * vec[:, 1]
        tcp = np.array([tx.mean(), ty.mean(), 0.0])
    return CircleFit(centre_plane, abs(rad), normal, rms, tcp, len(P))
