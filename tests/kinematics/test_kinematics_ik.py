"""``station.kinematics.ik``: batched damped-least-squares IK, checked by forward kinematics."""

from __future__ import annotations

import numpy as np

from station.kinematics import load_model
from station.kinematics.ik import solve_ik

HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])


def test_poses_and_positions_from_nearby_seeds():
    m = load_model("ur5e")
    rng = np.random.default_rng(5)
    q_true = HOME + rng.uniform(-0.3, 0.3, (8, 6))
    targets = m.fk(q_true)
    seeds = q_true + rng.uniform(-0.1, 0.1, q_true.shape)
    res = solve_ik(m, targets, seeds)
    assert res.ok.all() and res.position_error.max() < 1e-6 and res.orientation_error.max() < 1e-5
    T = m.fk(res.q)  # the answer checked by forward kinematics, not by the solver's own error
    assert np.abs(T[:, :3, 3] - targets[:, :3, 3]).max() < 1e-6
    assert np.abs(T[:, :3, :3] - targets[:, :3, :3]).max() < 1e-5
    pos = solve_ik(m, targets[:, :3, 3], seeds)  # position only: orientation left free
    assert pos.ok.all() and np.abs(m.fk(pos.q)[:, :3, 3] - targets[:, :3, 3]).max() < 1e-6


def test_out_of_reach_is_not_ok_and_stays_within_limits():
    m = load_model("ur5e")
    res = solve_ik(m, np.array([[5.0, 0.0, 0.5]]), HOME, max_iter=50)
    assert not res.ok[0] and res.position_error[0] > 3.0
    assert m.within_limits(res.q).all()


def test_weights_keep_a_redundant_arm_near_its_seed():
    """A position-only target on a 6-joint arm (3 spare DOF): a joint with a tiny weight barely moves."""
    m = load_model("ur5e")
    goal = m.fk(HOME + np.array([0.05, 0.05, -0.05, 0, 0, 0]))[:3, 3]
    w = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1e-3])
    res = solve_ik(m, goal, HOME, weights=w)
    assert res.ok[0]
    assert abs(res.q[0, 5] - HOME[5]) < 1e-3
