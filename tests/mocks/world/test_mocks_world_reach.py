"""``station.mocks.world.reach``: where an arm of one's own reaches a cell point from a wide cone, checked by
forward kinematics of the configurations it returns."""

from __future__ import annotations

import numpy as np
from station.mocks.world.reach import CONE, MIN_SCORE, cone_scores, workspace_reach

from station.kinematics import load_model


def test_cone_scores_and_their_configurations():
    m = load_model("ur5e")
    points = np.array([[0.45, 0.15, 0.10], [3.0, 0.0, 0.1]])  # one in comfortable reach, one 3 m away
    score, q = cone_scores(m, points, seed=1)
    assert score[0] > MIN_SCORE and score[1] == 0.0
    ok = ~np.isnan(q[0, :, 0])
    T = m.fk(q[0, ok])
    assert np.abs(T[:, :3, 3] - points[0]).max() < 1e-5  # every returned configuration touches the point
    tool_z = T[:, :3, 2]
    tilt = np.arccos(np.clip(-tool_z[:, 2], -1, 1))  # the tool points down into the socket, within the cone
    assert tilt.max() <= CONE + 1e-3 and tilt.max() > 0.5 * CONE  # and the cone is used, not one direction
    assert m.within_limits(q[0, ok]).all()
    assert (T[:, 2, 3] > 0).all()


def test_workspace_reach_of_a_ur5e():
    r, h, P = workspace_reach(load_model("ur5e"), np.random.default_rng(0), n=2000)
    assert 0.7 < r < 0.95  # the UR5e's published reach is 850 mm
    # no sample beyond the arm: UR's DH table, a2 + a3 + d4 + d5 + d6 at most
    assert P.shape == (2000, 3) and np.hypot(P[:, 0], P[:, 1]).max() < 0.425 + 0.3922 + 0.1333 + 0.0997 + 0.0996
