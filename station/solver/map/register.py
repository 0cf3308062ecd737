"""Registration of a measuring instrument's frame to the robot base frame (a laser tracker reports in its own
frame; the map's GDK(x) is in the base frame).

The instrument's pose in the base frame is the least-squares rigid fit (Kabsch) of the measured tool frames
to the tool frames the model gives at the same actuator readings: each frame contributes its origin and, for
6-DoF measurements, three points ``LEVER`` along its axes, so orientation and position both count. The part of
the robot's errors that looks like a rigid motion of the whole workspace is absorbed by the fit (it is
indistinguishable from where the instrument stands); the map corrects the rest. Pure: arrays in and out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.kinematics import se3
from station.solver.map.poses import FULL, POSITION, MapError

LEVER = 0.1  # m: axis points of a 6-DoF frame, so 1 mrad of orientation weighs like 0.1 mm of position


@dataclass(frozen=True)
class Registration:
    instrument_in_base: np.ndarray  # 4x4 SI
    rms: float  # m: RMS distance of the fitted points (origins and axis points) after the fit
    n: int  # frames used

    def to_base(self, measured: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
        """Pose vectors measured in the instrument frame -> the same in the base frame."""
        v = np.atleast_2d(np.asarray(measured, dtype=float))
        T = self.instrument_in_base
        out = v.copy()
        out[:, :3] = v[:, :3] @ T[:3, :3].T + T[:3, 3]
        if cols == FULL:
            out[:, 3:] = se3.matrix_to_rotvec(T[:3, :3] @ se3.rotvec_to_matrix(v[:, 3:]))
        return out

    def to_dict(self) -> dict:
        return {"instrument_in_base": se3.matrix_to_pose(self.instrument_in_base, "rotvec").tolist(),
                "rms_m": self.rms, "n": self.n, "rotation": "rotvec", "units": "m, rad"}


def _points(v: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
    if cols == FULL:
        R = se3.rotvec_to_matrix(v[:, 3:])
        axes = v[:, None, :3] + LEVER * np.swapaxes(R, 1, 2)  # origin + LEVER * column k of R
        return np.concatenate([v[:, None, :3], axes], axis=1).reshape(-1, 3)
    return v[:, :3]


def register(nominal_base: np.ndarray, measured: np.ndarray, cols: tuple[str, ...]) -> Registration:
    """Fit the instrument frame: ``nominal_base`` = the model's tool poses (pose vectors, base frame),
    ``measured`` = the instrument's readings of the same frames (its own frame), both with columns ``cols``
    (``x,y,z`` or ``x,y,z,rx,ry,rz``)."""
    if cols not in (FULL, POSITION):
        raise MapError(f"registration needs pose columns x,y,z or x,y,z,rx,ry,rz, got {','.join(cols)}")
    a = _points(np.atleast_2d(np.asarray(measured, dtype=float)), cols)
    b = _points(np.atleast_2d(np.asarray(nominal_base, dtype=float)), cols)
    if len(a) < 3 or np.linalg.matrix_rank(a - a.mean(axis=0), tol=1e-6) < 2:
        raise MapError("registration: the measured frames do not span a plane; measure more spread poses")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cb - R @ ca
    rms = float(np.sqrt(np.mean(np.sum((a @ R.T + T[:3, 3] - b) ** 2, axis=1))))
    return Registration(T, rms, len(np.atleast_2d(measured)))
