"""The solver's own position Jacobian agrees with the kinematics layer's analytic one and with finite
differences, for every built-in model and every parameter."""

import numpy as np
import pytest

from station.kinematics import builtin_names, load_model
from station.solver.problem import position_jacobian


@pytest.mark.parametrize("name", [n for n in builtin_names() if load_model(n).convention != "parallel"])
def test_position_jacobian_matches_kinematics(name):
    m = load_model(name)
    rng = np.random.default_rng(0)
    params = m.params + rng.normal(0, 0.01, m.params.shape)
    q = rng.uniform(-1, 1, (7, m.n_joints))
    idx = np.arange(len(m.param_names))
    P, J = position_jacobian(m.chain, q, params, idx)
    T, _, Jp = m.jacobians(q, params)
    np.testing.assert_allclose(P, T[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(J, Jp[:, :3, :], atol=1e-12)
    sub = idx[::3]
    _, Js = position_jacobian(m.chain, q, params, sub)
    np.testing.assert_allclose(Js, Jp[:, :3, sub], atol=1e-12)
    h = 1e-7
    k = int(sub[len(sub) // 2])
    dp = params.copy()
    dp[k] += h
    fd = (m.position(q, dp) - m.position(q, params)) / h
    np.testing.assert_allclose(J[:, :, k], fd, atol=1e-6)


def test_initial_point_guess_shortcut_matches_the_plain_path():
    from station.solver import Observations
    from station.solver.problem import Problem

    m = load_model("ur5e").with_params({"tcp.z": 0.1})
    rng = np.random.default_rng(3)
    q = rng.uniform(-1, 1, (12, 6))
    obs = Observations(q, ["A", "B", "C"] * 4)
    prob = Problem(m, obs, m.select("offsets,tcp"), {"C": np.array([0.1, 0.2, 0.3])})
    x, r, J = prob.initial_with_jacobian()
    x2 = prob.initial()
    r2, J2 = prob.residual_jacobian(x2)
    np.testing.assert_allclose(x, x2, atol=1e-15)
    np.testing.assert_allclose(r, r2, atol=1e-15)
    np.testing.assert_allclose(J, J2, atol=1e-15)
