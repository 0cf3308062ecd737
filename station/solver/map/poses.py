"""Pose components of the map: which columns fix a configuration of which robot, and conversions between
pose vectors (position m, rotation vector rad, base frame) and 4x4 transforms."""

from __future__ import annotations

import numpy as np

from station.kinematics import se3

PLANAR = ("x", "y")
POSITION = ("x", "y", "z")
FULL = ("x", "y", "z", "rx", "ry", "rz")


class MapError(ValueError):
    """Bad input to the map or a point it cannot serve; one line. ``row`` (0-based) names the offending
    configuration or pose when there is one."""

    def __init__(self, message: str, row: int | None = None) -> None:
        super().__init__(message)
        self.row = row


def is_parallel(model) -> bool:
    return getattr(model, "kind", "serial") == "parallel"


def output_columns(model) -> tuple[str, ...]:
    """The pose a configuration gives: ``x, y`` for the planar robot, else position + rotation vector."""
    return tuple(model.pose_columns) if is_parallel(model) else FULL


def check_columns(model, cols: tuple[str, ...], what: str) -> tuple[str, ...]:
    """``cols`` if they fix a configuration of ``model`` (else a one-line MapError naming the choices)."""
    cols = tuple(cols)
    if is_parallel(model):
        need = tuple(model.pose_columns)
        if cols != need:
            raise MapError(f"{what}: model {model.name} ({model.type}) needs pose columns {','.join(need)}, "
                           f"got {','.join(cols) or 'none'}")
        return cols
    if cols == FULL or (cols == POSITION and model.n_joints <= 3):
        return cols
    if cols == POSITION:
        if what.startswith("samples"):
            return cols  # measured positions only: the summand is the smallest joint change explaining them
        raise MapError(f"{what}: model {model.name} has {model.n_joints} joints: a position leaves the "
                       f"configuration open, give x,y,z,rx,ry,rz")
    raise MapError(f"{what}: pose columns must be x,y,z or x,y,z,rx,ry,rz, got {','.join(cols) or 'none'}")


def to_vectors(T: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
    """``(N,4,4)`` -> ``(N, len(cols))``."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    if cols == FULL:
        return se3.matrix_to_pose(T, "rotvec")
    return T[:, :len(cols), 3].copy()


def to_targets(v: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
    """Pose vectors -> IK targets: ``(N,4,4)`` for a full pose, else positions ``(N, len(cols))``."""
    v = np.atleast_2d(np.asarray(v, dtype=float))
    if cols == FULL:
        return se3.pose_to_matrix(v, "rotvec")
    return v.copy()


def pose_difference(T: np.ndarray, v: np.ndarray, cols: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Position error (m) and orientation error (rad, 0 without rotation columns) of poses ``T`` against
    pose vectors ``v``."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    v = np.atleast_2d(v)
    k = 3 if len(cols) >= 3 else 2
    dp = np.linalg.norm(T[:, :k, 3] - v[:, :k], axis=1)
    if cols != FULL:
        return dp, np.zeros(len(dp))
    dr = np.linalg.norm(se3.orientation_error(se3.rotvec_to_matrix(v[:, 3:]), T[:, :3, :3]), axis=1)
    return dp, dr
