"""``station.solver.misfit`` called directly (``tests/solver/test_solver_misfit.py`` goes through ``solve``): the
explanation of residuals simulated with a known cause (joint play, a wrong tool, backlash), and the small NNLS
against scipy's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls

from station.kinematics import load_model
from station.solver.misfit import _nnls, explain, joint_play, nothing_improved

HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
NAMES = [f"j{i}" for i in range(1, 7)]


@pytest.mark.parametrize("seed", range(5))
def test_nnls_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    A, y = rng.normal(size=(30, 7)), rng.normal(size=30)
    assert np.allclose(_nnls(A, y), nnls(A, y)[0], atol=1e-9)


def _touches(n, seed):
    rng = np.random.default_rng(seed)
    m = load_model("ur5e")
    q = HOME + np.cumsum(rng.uniform(-0.05, 0.05, (n, 6)), axis=0)  # recording order: a random walk
    return m, q, m.jacobian_q(q)[:, :3], rng


def test_joint_play_separates_tip_noise_from_a_joints_reading_noise():
    m, q, Jq, rng = _touches(3000, 1)
    s_tip, s_j3 = 30e-6, 2e-4
    r = rng.normal(0, s_tip, (len(q), 3)) + Jq[:, :, 2] * rng.normal(0, s_j3, (len(q), 1))
    tip, joint_sd, share = joint_play(r, Jq)
    assert tip == pytest.approx(s_tip, rel=0.1) and joint_sd[2] == pytest.approx(s_j3, rel=0.1)
    assert share[2] > 3 * np.delete(share, 2).max()  # (j4, parallel to j3 on a short lever, takes a little)


def _explain(m, q, r, Jtcp=None):
    keys = np.zeros(len(q), dtype=int)
    return explain(q, keys, r, np.ones(len(q), bool), m.jacobian_q(q)[:, :3], Jtcp, 1e-3, 0.9e-3, 1e-3, "socket",
                   NAMES, [True] * 6)


def test_backlash_is_named_with_its_joint_and_size():
    m, q, Jq, rng = _touches(200, 2)
    b = np.radians(0.2)  # full play of joint 2
    s = np.zeros_like(q)
    s[1:] = np.sign(np.diff(q, axis=0))
    r = Jq[:, :, 1] * (0.5 * b * s[:, 1:2]) + rng.normal(0, 5e-6, (len(q), 3))
    out = _explain(m, q, r)
    assert out["cause"] == "backlash" and "j2 0.2 deg" in out["evidence"], out["line"]
    assert out["line"].startswith("nothing to trust: ") and "\n" not in out["line"]


def test_a_wrong_tool_is_named():
    m, q, _, rng = _touches(200, 3)
    T = m.fk(q)
    d = np.array([0.0, 0.0, 0.004])  # 4 mm longer tool than the model's, in the flange frame
    r = np.einsum("nij,j->ni", T[:, :3, :3], d) + rng.normal(0, 5e-6, (len(q), 3))
    out = _explain(m, q, r, Jtcp=T[:, :3, :3])
    assert out["cause"] == "wrong tip link or tool", out["line"]


def test_a_good_fit_needs_no_explanation():
    assert not nothing_improved(1e-3, 0.05e-3, 0.04e-3, "socket")
    assert nothing_improved(1e-3, 0.95e-3, 0.2e-3, "socket")  # stuck above 3x the method's noise
    assert nothing_improved(1e-3, 0.1e-3, 0.6e-3, "socket")  # far above it
    m, q, _, _ = _touches(20, 4)
    assert explain(q, np.zeros(20, int), np.zeros((20, 3)), np.ones(20, bool), m.jacobian_q(q)[:, :3], None,
                   1e-3, 0.04e-3, 0.04e-3, "socket", NAMES, [True] * 6) is None
