"""Small SE(3) helpers, vectorised over leading axes. Angles in rad, lengths in m."""

from __future__ import annotations

import warnings

import numpy as np


def _rotation():
    """scipy's Rotation, imported on first use: importing scipy.spatial costs ~0.4 s, and most commands
    (``station solve``, ``station fk --help``) never need it."""
    from scipy.spatial.transform import Rotation

    return Rotation


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """Fixed-axis roll-pitch-yaw: ``R = Rz(rz) Ry(ry) Rx(rx)``; input ``(..., 3)`` as (rx, ry, rz)."""
    return _rotation().from_euler("ZYX", np.asarray(rpy)[..., ::-1]).as_matrix()


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix`, returns ``(..., 3)`` as (rx, ry, rz). At pitch +-90 deg (gimbal
    lock) roll and yaw are not unique: scipy sets one of them to zero, still an exact decomposition."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        return _rotation().from_matrix(R).as_euler("ZYX")[..., ::-1]


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """Axis-angle rotation vector (as a UR controller reports rx, ry, rz) to rotation matrix."""
    return _rotation().from_rotvec(rv).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    return _rotation().from_matrix(R).as_rotvec()


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
    return _rotation().from_matrix(R_target @ np.swapaxes(R, -1, -2)).as_rotvec()
