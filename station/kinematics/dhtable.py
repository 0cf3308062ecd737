"""The exact standard-DH table of a revolute chain, whatever convention its model is written in.

A controller that stores its kinematics as plain DH rows (Universal Robots: ``theta, a, d, alpha`` per joint,
published table plus factory deltas) describes each joint axis by the common normal to the next one. Two
nearly parallel axes meet far away, so their common normal sits there: a tilt of 1e-3 rad between axes
0.4 m apart puts it ~400 m out along the axis (``d`` of hundreds of metres, ``theta`` near +-pi/2), and the
next row's ``d`` walks back. Those numbers are exact, only unhandy. ``dh_table`` computes them from any
model's joint axes (it is what such a controller reports for that arm), so that

    model.fk(q) == table.base @ prod_i Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) @ table.flange

at every ``q`` (lengths m, angles rad; ``base``/``flange`` are identity for a standard-DH model without base,
tool or Hayati tilt of its last link). Rigid geometry only: a model's gravity deflection is not part of it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from station.kinematics.chain import RX, RY, RZ, forward
from station.kinematics.se3 import invert

_PARALLEL = 1e-12  # |z x w| below this: the axes are parallel to machine precision (common normal free)


@dataclass(frozen=True)
class DHTable:
    """Rows of a standard-DH chain (SI): joint i turns ``Rz(q_i + theta[i]) Tz(d[i]) Tx(a[i]) Rx(alpha[i])``;
    ``base`` is the model's root -> DH frame 0 (z on joint 1's axis), ``flange`` DH frame n -> the model's
    tool frame."""

    theta: np.ndarray
    d: np.ndarray
    a: np.ndarray
    alpha: np.ndarray
    base: np.ndarray
    flange: np.ndarray

    @property
    def n(self) -> int:
        return len(self.theta)

    def rows(self) -> np.ndarray:
        """``(n, 4)`` columns theta, d, a, alpha."""
        return np.column_stack([self.theta, self.d, self.a, self.alpha])

    def fk(self, q) -> np.ndarray:
        """``base @ rows(q) @ flange``: ``(N,4,4)``, or ``(4,4)`` for one joint vector."""
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        q = np.atleast_2d(q)
        T = np.broadcast_to(self.base, (len(q), 4, 4)).copy()
        for i in range(self.n):
            T = T @ link(self.theta[i] + q[:, i], self.d[i], self.a[i], self.alpha[i])
        T = T @ self.flange
        return T[0] if single else T


def link(theta, d: float, a: float, alpha: float) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` for an array of ``theta``: ``(N,4,4)``."""
    th = np.atleast_1d(np.asarray(theta, dtype=float))
    c, s = np.cos(th), np.sin(th)
    ca, sa = math.cos(alpha), math.sin(alpha)
    T = np.zeros((len(th), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2], T[:, 0, 3] = c, -s * ca, s * sa, a * c
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = s, c * ca, -c * sa, a * s
    T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = sa, ca, d
    T[:, 3, 3] = 1.0
    return T


def _wrap_near(angle: float, hint: float) -> float:
    return hint + (angle - hint + math.pi) % (2 * math.pi) - math.pi


def joint_axes(model, params=None) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """``(frame0, axes, tool)`` at ``q = 0``: the frame before joint 1's element turned so that z is that
    joint's axis, each joint's axis as a frame (z = axis, origin on it; model root coordinates), and the tool
    frame. Revolute joints only."""
    p = model.params if params is None else np.asarray(params, dtype=float)
    n = model.n_joints
    T, prefix = forward(model.chain, np.zeros((1, n)), p, keep_prefix=True)
    axes = []
    for i, jt in enumerate(model.joints):
        if not jt.revolute:
            raise ValueError(f"model {model.name}: joint {i + 1} is prismatic; a DH table here is for revolute "
                             "chains")
        k = int(np.flatnonzero(model.chain.joint == i)[0])
        F = prefix[0, k].copy()
        ax = int(model.chain.axis[k])
        if ax == RX:  # make the turning axis the frame's z (a cyclic permutation keeps it right-handed)
            F[:3, :3] = F[:3, [1, 2, 0]]
        elif ax == RY:
            F[:3, :3] = F[:3, [2, 0, 1]]
        elif ax != RZ:
            raise ValueError(f"model {model.name}: joint {i + 1} is not a rotation")
        axes.append(F)
    return axes[0], axes, T[0]


def dh_table(model, params=None, hint: DHTable | None = None) -> DHTable:
    """The exact standard-DH table of ``model`` (see the module docstring). Where DH leaves a choice (the sign
    of a common normal; ``d`` between exactly parallel axes) it follows ``hint`` (e.g. the published table of
    the arm), else theta nearest 0 and d = 0."""
    frame0, axes, tool = joint_axes(model, params)
    n = len(axes)
    th, dd, aa, al = (np.zeros(n) for _ in range(4))
    hint_frames = None
    if hint is not None:
        hint_frames = [hint.base]
        for i in range(n):
            hint_frames.append(hint_frames[-1] @ link(hint.theta[i], hint.d[i], hint.a[i], hint.alpha[i])[0])
    F = frame0  # DH frame i-1 in root coordinates: z on axis i
    for i in range(n):
        h_th = float(hint.theta[i]) if hint is not None else 0.0
        if i < n - 1:
            L = invert(F) @ axes[i + 1]  # the next axis in frame i-1
            p, w = L[:3, 3], L[:3, 2]
            cross = np.array([-w[1], w[0], 0.0])  # e3 x w
            if np.linalg.norm(cross) < _PARALLEL:
                d = float(hint.d[i]) if hint is not None else 0.0
                foot = np.array([0.0, 0.0, d])
                x = np.array([p[0], p[1], 0.0])
                r = float(np.linalg.norm(x))
                x = x / r if r > 0 else np.array([1.0, 0.0, 0.0])
            else:
                # the common normal is along e3 x w whatever the distance of the axes (robust when they are
                # nearly parallel and meet far away); its foot on axis i is where d is
                x = cross / np.linalg.norm(cross)
                # the foot of the normal on the next axis: where that axis crosses the plane of axis i and x
                y2 = np.array([-x[1], x[0], 0.0])
                P = p - (float(p @ y2) / float(w @ y2)) * w
                d, r = float(P[2]), float(P @ x)
                foot = np.array([0.0, 0.0, d])
            # the sign of the normal: the frame nearest the hint's frame i (a published table's negative a stays
            # negative, and its alpha keeps its sign), else theta nearest 0
            t1 = math.atan2(x[1], x[0])
            t2 = math.atan2(-x[1], -x[0])
            if hint_frames is not None:
                flip = float((F[:3, :3] @ x) @ hint_frames[i + 1][:3, 0]) < 0
            else:
                flip = abs(_wrap_near(t2, h_th) - h_th) < abs(_wrap_near(t1, h_th) - h_th)
            if flip:
                x, r, t1 = -x, -r, t2
            theta = _wrap_near(t1, h_th)
            y = np.cross(w, x)
            alpha = math.atan2(float(np.cross([0.0, 0.0, 1.0], w) @ x), float(w[2]))
            nxt = np.eye(4)
            nxt[:3, 0], nxt[:3, 1], nxt[:3, 2] = x, y / np.linalg.norm(y), w
            nxt[:3, 3] = foot + r * x
            th[i], dd[i], aa[i], al[i] = theta, d, r, alpha
            F = F @ nxt
        else:  # the last row: as much of the tool frame as one DH row holds; the rest is ``flange``
            R = invert(F) @ tool
            theta = _wrap_near(math.atan2(R[1, 0], R[0, 0]), h_th)
            ct, st = math.cos(theta), math.sin(theta)
            d = float(R[2, 3])
            a = float(R[0, 3] * ct + R[1, 3] * st)
            zf = R[:3, 2]
            alpha = math.atan2(-float(zf @ np.array([-st, ct, 0.0])), float(zf[2]))
            th[i], dd[i], aa[i], al[i] = theta, d, a, alpha
            F = F @ link(theta, d, a, alpha)[0]
    return DHTable(th, dd, aa, al, frame0, invert(F) @ tool)
