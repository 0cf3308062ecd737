"""The folded chain (constant runs multiplied once per problem) gives the same positions and Jacobian as the
unfolded chain pass and the kinematics layer, for every built-in model and several parameter subsets."""

import numpy as np
import pytest

from station.kinematics import builtin_names, load_model
from station.solver.folded import FoldedChain
from station.solver.problem import position_jacobian


def _subsets(m, rng):
    n = len(m.param_names)
    everything = np.arange(n)
    return {
        "all": everything,
        "every third": everything[::3],
        "offsets+tcp": np.array([m.index(s) for s in m.select("offsets,tcp")]),
        "shuffled": rng.permutation(n)[: n // 2],  # columns not in chain order
        "none": np.zeros(0, dtype=int),
    }


@pytest.mark.parametrize("name", [n for n in builtin_names() if load_model(n).convention != "parallel"])
def test_folded_chain_equals_unfolded_chain(name):
    m = load_model(name)
    rng = np.random.default_rng(1)
    params = m.params + rng.normal(0, 0.01, m.params.shape)
    q = rng.uniform(-1.5, 1.5, (9, m.n_joints))
    T, _, Jp = m.jacobians(q, params)
    for label, idx in _subsets(m, rng).items():
        fc = FoldedChain(m.chain, params, idx)
        P, J = fc.evaluate(q, params)
        P0, J0 = position_jacobian(m.chain, q, params, idx)
        np.testing.assert_allclose(P, P0, atol=1e-12, err_msg=label)
        np.testing.assert_allclose(P, T[:, :3, 3], atol=1e-12, err_msg=label)
        np.testing.assert_allclose(J, J0, atol=1e-12, err_msg=label)
        np.testing.assert_allclose(J, Jp[:, :3, idx], atol=1e-12, err_msg=label)
        Pn, Jn = fc.evaluate(q, params, jacobian=False)
        assert Jn is None
        np.testing.assert_allclose(Pn, P, atol=1e-15)
        if len(idx) < len(m.param_names):
            assert fc.n_items < m.chain.n_elements - m.n_joints  # something was folded


def test_folded_chain_follows_the_identified_values_and_writes_into_out():
    m = load_model("ur5e")
    idx = np.array([m.index(s) for s in m.select("offsets,tcp,dh.j2.*")])
    fc = FoldedChain(m.chain, m.params, idx)
    rng = np.random.default_rng(2)
    q = rng.uniform(-2, 2, (5, 6))
    p = m.params.copy()
    p[idx] += rng.normal(0, 0.05, len(idx))  # only the identified ones move: the rest is folded in
    out = np.full((15, len(idx) + 4), np.nan)
    view = out[:, 2: 2 + len(idx)]
    view.shape = (5, 3, len(idx))
    P, J = fc.evaluate(q, p, out=view)
    assert J is view
    T, _, Jp = m.jacobians(q, p)
    np.testing.assert_allclose(P, T[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(out[:, 2: 2 + len(idx)].reshape(5, 3, -1), Jp[:, :3, idx], atol=1e-12)
    assert np.isnan(out[:, :2]).all() and np.isnan(out[:, 2 + len(idx):]).all()
    # a single pose, and finite differences on an identified angle
    k = int(np.flatnonzero(idx == m.index("dh.j2.alpha"))[0])
    h = 1e-7
    p2 = p.copy()
    p2[idx[k]] += h
    fd = (fc.evaluate(q[0], p2, jacobian=False)[0] - fc.evaluate(q[0], p, jacobian=False)[0]) / h
    np.testing.assert_allclose(fd[0], J[0, :, k], atol=1e-6)


def test_compiled_cache_is_per_model_and_selection():
    from station.solver.problem import compiled

    m = load_model("ur5e")
    idx = np.array([m.index(s) for s in m.select("offsets,tcp")])
    a = compiled(m, idx)
    assert compiled(m, idx.copy()) is a  # same model, same selection: compiled once
    assert compiled(m, idx[:-1]) is not a
    m2 = m.with_params({"dh.j2.a": m.param("dh.j2.a") + 0.01})
    f2 = compiled(m2, idx)[0]
    assert f2 is not a[0]
    q = np.random.default_rng(0).uniform(-1, 1, (4, 6))
    np.testing.assert_allclose(f2.evaluate(q, m2.params)[0], m2.position(q), atol=1e-12)
    # a parameter array changed in place (models are immutable by contract, but never serve stale numbers)
    m3 = m.with_params({})
    f3 = compiled(m3, idx)[0]
    m3.params[m3.index("dh.j3.a")] += 0.02
    f3b = compiled(m3, idx)[0]
    assert f3b is not f3
    np.testing.assert_allclose(f3b.evaluate(q, m3.params)[0], m3.position(q), atol=1e-12)


def test_first_joint_shift_equals_a_chain_pass():
    """Changing the first joint's offset is a rigid motion of every tool position and model column: the
    shortcut the solver takes when only that offset is dropped equals a fresh evaluation."""
    from station.solver import Observations
    from station.solver.problem import Problem

    m = load_model("ur5e").with_params({"tcp.z": 0.1})
    rng = np.random.default_rng(3)
    q = rng.uniform(-1, 1, (12, 6))
    obs = Observations(q, ["A", "B", "C"] * 4)
    for ref in ("unknown", {"C": np.array([0.1, 0.2, 0.3])}):
        prob = Problem(m, obs, m.select("offsets,tcp,dh.j3.*"), ref)
        c = prob.first_joint_offset_column()
        assert prob.names[c] == "offset.j1"
        x = prob.initial() + rng.normal(0, 1e-3, prob.n_unknowns)
        for scaled in (False, True):
            r, J = prob.residual_jacobian(x, scaled)
            r2, J2 = prob.shift_first_joint(x, r, J, 0.05)
            x2 = x.copy()
            x2[c] += 0.05
            r3, J3 = prob.residual_jacobian(x2, scaled)
            np.testing.assert_allclose(r2, r3, atol=1e-12)
            np.testing.assert_allclose(J2, J3, atol=1e-12)
    # not applicable when an identified element precedes the first joint (instrument frame base.*)
    prob = Problem(m, Observations(q, measured=m.position(q)), m.select("offsets,tcp"), "unknown")
    assert prob.first_joint_offset_column() == -1
