"""Small SE(3) helpers, vectorised over leading axes. Angles in rad, lengths in m."""

from __future__ import annotations

import numpy as np


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def frame_with_z(z: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """A rotation whose z axis is ``z`` (any length), turned by ``roll`` about it: the x axis is the one of the base
    x or y axes least aligned with z, projected square to z (a definite frame for every direction)."""
    z = np.asarray(z, float) / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - z * (helper @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """Fixed-axis roll-pitch-yaw: ``R = Rz(rz) Ry(ry) Rx(rx)``; input ``(..., 3)`` as (rx, ry, rz)."""
    rpy = np.asarray(rpy, dtype=float)
    cx, cy, cz = np.cos(rpy[..., 0]), np.cos(rpy[..., 1]), np.cos(rpy[..., 2])
    sx, sy, sz = np.sin(rpy[..., 0]), np.sin(rpy[..., 1]), np.sin(rpy[..., 2])
    R = np.empty(rpy.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sy, cy * sx, cy * cx
    return R


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix`, returns ``(..., 3)`` as (rx, ry, rz), ry in [-90, 90] deg. At pitch
    +-90 deg (gimbal lock) roll and yaw are not unique: roll is set to zero, still an exact decomposition."""
    R = np.asarray(R, dtype=float)
    cy = np.hypot(R[..., 0, 0], R[..., 1, 0])
    lock = cy == 0.0  # exactly at +-90 deg pitch: roll 0 (any other cy is decomposed exactly below)
    # locked: R = Rz(rz) Ry(+-90): R01 = -sin(rz), R11 = cos(rz) with roll 0
    rz = np.where(lock, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    # roll and pitch from Rz(-rz) R = Ry(ry) Rx(rx), whose second row is (0, cos rx, -sin rx) at every pitch:
    # atan2(R21, R22) would divide two numbers of size cos(ry) and lose all digits near gimbal lock
    c, s = np.cos(rz), np.sin(rz)
    r00 = c * R[..., 0, 0] + s * R[..., 1, 0]
    r11 = -s * R[..., 0, 1] + c * R[..., 1, 1]
    r12 = -s * R[..., 0, 2] + c * R[..., 1, 2]
    ry = np.arctan2(-R[..., 2, 0], r00)
    rx = np.where(lock, 0.0, np.arctan2(-r12, r11))
    return np.stack([rx, ry, rz], axis=-1)


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Axis-angle rotation vector (as a UR controller reports rx, ry, rz) to rotation matrix (Rodrigues)."""
    rv = np.asarray(rv, dtype=float)
    th2 = np.sum(rv * rv, axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-6
    safe = np.where(small, 1.0, th)
    # sin(t)/t and (1 - cos t)/t^2, with their series where t is tiny (no 0/0)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = np.zeros(rv.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -rv[..., 2], rv[..., 1], -rv[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = rv[..., 2], -rv[..., 1], rv[..., 0]
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to rotation vector, angle in [0, pi]: through the unit quaternion (Shepperd's choice of
    the largest component, so it stays accurate near 180 deg where the axis comes from the symmetric part)."""
    R = np.asarray(R, dtype=float)
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    d = np.stack([R[..., 0, 0], R[..., 1, 1], R[..., 2, 2], tr], axis=-1)
    k = np.argmax(d, axis=-1)
    q = np.empty(R.shape[:-2] + (4,))  # x, y, z, w
    for i in range(3):
        j, m = (i + 1) % 3, (i + 2) % 3
        sel = k == i
        if np.any(sel):
            Rs = R[sel]
            qi = np.sqrt(np.maximum(1.0 + 2.0 * Rs[:, i, i] - tr[sel], 0.0)) / 2.0
            qs = np.empty((len(Rs), 4))
            qs[:, i] = qi
            qs[:, j] = (Rs[:, j, i] + Rs[:, i, j]) / (4.0 * qi)
            qs[:, m] = (Rs[:, m, i] + Rs[:, i, m]) / (4.0 * qi)
            qs[:, 3] = (Rs[:, m, j] - Rs[:, j, m]) / (4.0 * qi)
            q[sel] = qs
    sel = k == 3
    if np.any(sel):
        Rs = R[sel]
        w = np.sqrt(np.maximum(1.0 + tr[sel], 0.0)) / 2.0
        q[sel] = np.stack([(Rs[:, 2, 1] - Rs[:, 1, 2]) / (4 * w), (Rs[:, 0, 2] - Rs[:, 2, 0]) / (4 * w),
                           (Rs[:, 1, 0] - Rs[:, 0, 1]) / (4 * w), w], axis=-1)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., 3:4] < 0, -q, q)  # w >= 0: angle in [0, pi]
    v = np.linalg.norm(q[..., :3], axis=-1)
    angle = 2.0 * np.arctan2(v, q[..., 3])
    small = v < 1e-12
    scale = np.where(small, 2.0 / np.where(small, q[..., 3], 1.0), angle / np.where(small, 1.0, v))
    return q[..., :3] * scale[..., None]


def pose_to_matrix(pose: np.ndarray, rotation: str = "rotvec") -> np.ndarray:
    """``(..., 6)`` x, y, z, rx, ry, rz -> ``(..., 4, 4)``; ``rotation`` is ``rotvec`` or ``rpy``."""
    pose = np.asarray(pose, dtype=float)
    T = np.zeros(pose.shape[:-1] + (4, 4))
    conv = rotvec_to_matrix if rotation == "rotvec" else rpy_to_matrix
    T[..., :3, :3] = conv(pose[..., 3:6])
    T[..., :3, 3] = pose[..., :3]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose(T: np.ndarray, rotation: str = "rotvec") -> np.ndarray:
    T = np.asarray(T, dtype=float)
    conv = matrix_to_rotvec if rotation == "rotvec" else matrix_to_rpy
    return np.concatenate([T[..., :3, 3], conv(T[..., :3, :3])], axis=-1)


def invert(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def orientation_error(R_target: np.ndarray, R: np.ndarray) -> np.ndarray:
    """World-frame rotation vector taking ``R`` to ``R_target``."""
    return matrix_to_rotvec(R_target @ np.swapaxes(R, -1, -2))
