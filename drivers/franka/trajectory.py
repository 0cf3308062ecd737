"""Joint-space point-to-point profiles the driver streams at 1 kHz (SI: rad, s).

A quintic from the state the arm is commanded in (position, velocity, acceleration) to rest at the target:
continuous in position, velocity and acceleration, so jerk is bounded; its duration is the shortest that keeps
every joint within the requested speed, the acceleration and jerk caps and Franka's position-based velocity
envelope (``drivers.franka.limits``) along the whole path."""

from __future__ import annotations

import numpy as np
from station.drivers.franka import limits

SAMPLES = 60  # points along the path where the envelope is checked


class Quintic:
    """``p(t)`` for ``t`` in [0, T] per joint, rest at the end; ``sample(t)`` clamps ``t`` to [0, T]."""

    def __init__(self, p0, v0, a0, p1, T: float) -> None:
        p0, v0, a0, p1 = (np.asarray(x, float) for x in (p0, v0, a0, p1))
        self.T = float(T)
        T = self.T
        d = p1 - p0 - v0 * T - 0.5 * a0 * T ** 2
        dv = -v0 - a0 * T
        da = -a0
        # the coefficients of t^3, t^4, t^5 that reach (p1, 0, 0) at T
        M = np.array([[T ** 3, T ** 4, T ** 5], [3 * T ** 2, 4 * T ** 3, 5 * T ** 4],
                      [6 * T, 12 * T ** 2, 20 * T ** 3]])
        c = np.linalg.solve(M, np.vstack([d, dv, da]))
        self.c = np.vstack([p0, v0, 0.5 * a0, c])  # (6, n): t^0 .. t^5

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = min(max(t, 0.0), self.T)
        c = self.c
        p = ((((c[5] * t + c[4]) * t + c[3]) * t + c[2]) * t + c[1]) * t + c[0]
        v = (((5 * c[5] * t + 4 * c[4]) * t + 3 * c[3]) * t + 2 * c[2]) * t + c[1]
        a = ((20 * c[5] * t + 12 * c[4]) * t + 6 * c[3]) * t + 2 * c[2]
        return p, v, a

    def peaks(self, n: int = SAMPLES) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities, accelerations and jerks at ``n`` points (n, joints)."""
        t = np.linspace(0.0, self.T, n)[:, None]
        c = self.c
        P = ((((c[5] * t + c[4]) * t + c[3]) * t + c[2]) * t + c[1]) * t + c[0]
        V = (((5 * c[5] * t + 4 * c[4]) * t + 3 * c[3]) * t + 2 * c[2]) * t + c[1]
        A = ((20 * c[5] * t + 12 * c[4]) * t + 6 * c[3]) * t + 2 * c[2]
        J = (60 * c[5] * t + 24 * c[4]) * t + 6 * c[3]
        return P, V, A, J


def plan(p0, v0, a0, p1, speed: np.ndarray | float, accel: float, jerk: float) -> Quintic:
    """The shortest quintic from (p0, v0, a0) to rest at ``p1`` with every joint within ``speed`` (rad/s, per
    joint or one for all), ``accel``, ``jerk`` and the velocity envelope along the path."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    dist = float(np.max(np.abs(p1 - p0)))
    speed = np.broadcast_to(np.asarray(speed, float), p0.shape)
    # a rest-to-rest quintic peaks at 1.875 D/T, 5.77 D/T^2, 60 D/T^3: the starting guess
    D = np.abs(p1 - p0)
    T = max(0.01, float(np.max(1.875 * D / speed)), float(np.sqrt(np.max(5.78 * D / accel))),
            float(np.cbrt(np.max(60.0 * D / jerk))))
    if dist < 1e-9 and not np.any(v0) and not np.any(a0):
        return Quintic(p0, v0, a0, p1, T)
    for _ in range(25):  # at most 33 times the first guess
        q = Quintic(p0, v0, a0, p1, T)
        P, V, A, J = q.peaks()
        lo, up = limits.velocity_envelope(P)
        ok = (np.all(np.abs(V) <= speed * 1.001) and np.all(np.abs(A) <= accel * 1.001)
              and np.all(np.abs(J) <= jerk * 1.001) and np.all(lo <= V) and np.all(up >= V))
        if ok:
            return q
        T *= 1.15
    return q
