"""``station.drivers.franka.trajectory``: quintic point-to-point profiles checked by sampling them densely
(finite differences, independent of the planner's own peak estimate) against the caps and Franka's envelope."""

from __future__ import annotations

import numpy as np
import pytest
from station.drivers.franka import limits
from station.drivers.franka.trajectory import Quintic, plan

Q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])  # libfranka's ready pose


def dense(q: Quintic, n=4001):
    t = np.linspace(0, q.T, n)
    P = np.array([q.sample(x)[0] for x in t])
    dt = t[1] - t[0]
    V = np.gradient(P, dt, axis=0)
    A = np.gradient(V, dt, axis=0)
    J = np.gradient(A, dt, axis=0)
    return P, V, A, J


def test_boundary_conditions_from_a_moving_state():
    v0, a0 = np.full(7, 0.1), np.full(7, -0.2)
    q = Quintic(Q0, v0, a0, Q0 + 0.3, 1.2)
    p, v, a = q.sample(0.0)
    assert np.allclose(p, Q0) and np.allclose(v, v0) and np.allclose(a, a0)
    p, v, a = q.sample(5.0)  # clamped to the end: at rest on the target
    assert np.allclose(p, Q0 + 0.3) and np.allclose(v, 0, atol=1e-12) and np.allclose(a, 0, atol=1e-10)


@pytest.mark.parametrize("target, speed", [(Q0 + np.array([0.8, 0.3, -0.5, 0.4, 1.0, -0.6, 1.2]), 1.0),
                                           (np.r_[Q0[:3], limits.Q_MAX[3] - 0.02, Q0[4:]], 2.0)])
def test_the_plan_keeps_every_cap_and_the_envelope(target, speed):
    accel, jerk = 5.0, 2000.0
    q = plan(Q0, np.zeros(7), np.zeros(7), target, speed, accel, jerk)
    P, V, A, J = dense(q)
    assert np.abs(V).max() <= speed * 1.002 and np.abs(A[5:-5]).max() <= accel * 1.01
    assert np.abs(J[10:-10]).max() <= jerk * 1.02
    lo, up = limits.velocity_envelope(P)
    assert (up + 2e-3 >= V).all() and (lo - 2e-3 <= V).all()
    # and not needlessly slow: the binding cap is nearly reached
    assert max(np.abs(V).max() / speed, np.abs(A).max() / accel, np.abs(J).max() / jerk,
               np.max(V / np.where(up > 0.05, up, np.inf))) > 0.85
