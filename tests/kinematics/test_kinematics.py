"""Kinematics: analytic Jacobians against finite differences, DH against POE, model files and units."""

import numpy as np
import pytest

from station.kinematics import (
    ModelFileError,
    builtin_names,
    dump_model,
    from_mdh,
    from_poe,
    load_model,
    model_from_dict,
    screws_of,
)

RNG = np.random.default_rng(7)


def _random_q(m, n=5):
    lo, hi = np.maximum(m.lower, -np.pi), np.minimum(m.upper, np.pi)
    return lo + (hi - lo) * RNG.random((n, m.n_joints))


def _perturbed(m, scale=0.01):
    return m.params + scale * RNG.standard_normal(len(m.params))


def _fd(fun, x, h=1e-6):
    cols = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def _pose_vec(T, T0):
    """Position and small-angle orientation difference relative to T0 (world frame)."""
    from station.kinematics.se3 import orientation_error

    return np.concatenate([T[:, :3, 3], orientation_error(T[:, :3, :3], T0[:, :3, :3])], axis=1)


@pytest.mark.parametrize("name", builtin_names())
def test_param_jacobian_matches_finite_differences(name):
    m = load_model(name)
    q, p = _random_q(m), _perturbed(m)
    T0, _, Jp = m.jacobians(q, p)
    num = _fd(lambda x: _pose_vec(m.fk(q, x), T0), p)
    np.testing.assert_allclose(Jp, num, atol=1e-7)


@pytest.mark.parametrize("name", builtin_names())
def test_joint_jacobian_matches_finite_differences(name):
    m = load_model(name)
    q, p = _random_q(m), _perturbed(m)
    T0, Jq, _ = m.jacobians(q, p)
    num = np.stack([_fd(lambda x, i=i: _pose_vec(m.fk(x[None], p), T0[i:i + 1])[0], q[i]) for i in range(len(q))])
    np.testing.assert_allclose(Jq, num, atol=1e-7)


@pytest.mark.parametrize("name", [n for n in builtin_names() if load_model(n).convention != "parallel"])
def test_fused_chain_matches_the_element_chain(name):
    """fk and fk_and_jacobian_q go through the fused chain (runs of fixed elements pre-multiplied): the same
    tool transform as the element-by-element routine, and a joint Jacobian equal to finite differences of
    it -- for perturbed parameters, and for a parameter vector changed after the first call (no stale cache)."""
    from station.kinematics.chain import forward

    m = load_model(name)
    q = _random_q(m)
    for p in (_perturbed(m), _perturbed(m) * 1.001):
        T_el = forward(m.chain, q, p)
        np.testing.assert_allclose(m.fk(q, p), T_el, atol=1e-13)
        T, Jq = m.fk_and_jacobian_q(q, p)
        np.testing.assert_allclose(T, T_el, atol=1e-13)
        num = np.stack([_fd(lambda x, i=i, p=p, T0=T_el: _pose_vec(forward(m.chain, x[None], p), T0[i:i + 1])[0], q[i])
                        for i in range(len(q))])
        np.testing.assert_allclose(Jq, num, atol=1e-7)


@pytest.mark.parametrize("name", ["ur5e", "arm6", "scara", "omx"])
def test_poe_twin_reproduces_dh(name):
    dh = load_model(name).with_params({"base.z": 0.1, "tcp.x": 0.02, "tcp.z": 0.15, "tcp.ry": 0.3})
    screws, home = screws_of(dh)
    base = {k: dh.param(f"base.{k}") for k in ("x", "y", "z", "rx", "ry", "rz")}
    tool = {k: dh.param(f"tcp.{k}") for k in ("x", "y", "z", "rx", "ry", "rz")}
    poe = from_poe(name + "-poe", list(dh.joints), screws, home, base=base, tool=tool)
    q = _random_q(dh, 20)
    np.testing.assert_allclose(poe.fk(q), dh.fk(q), atol=1e-12)


def test_mdh_matches_dh_for_equivalent_table():
    dh = load_model("ur5e")
    # Craig form of the same arm: alpha/a of the previous link move to this one
    links, prev = [], {"a": 0.0, "alpha": 0.0}
    for i in range(6):
        d = {k: dh.param(f"dh.j{i + 1}.{k}") for k in ("a", "alpha", "d")}
        links.append({"alpha": prev["alpha"], "a": prev["a"], "d": d["d"], "theta": 0.0})
        prev = d
    tool = {"x": prev["a"], "rx": prev["alpha"]}
    mdh = from_mdh("ur5e-mdh", list(dh.joints), links, tool=tool)
    q = _random_q(dh, 10)
    np.testing.assert_allclose(mdh.position(q), dh.position(q), atol=1e-12)


def test_fk_is_vectorised_and_single_pose_shape():
    m = load_model("ur5e")
    q = _random_q(m, 7)
    assert m.fk(q).shape == (7, 4, 4)
    assert m.fk(q[0]).shape == (4, 4)
    np.testing.assert_allclose(m.fk(q)[3], m.fk(q[3]))


def test_ur5e_zero_pose_matches_published_geometry():
    np.testing.assert_allclose(load_model("ur5e").position(np.zeros(6)), [-0.8172, -0.2329, 0.0628], atol=1e-12)


@pytest.mark.parametrize("name", [n for n in builtin_names() if load_model(n).convention != "parallel"])
def test_export_roundtrip_in_other_units(name):
    import yaml

    m = load_model(name).with_params({"offset.j2": 0.01, "tcp.z": 0.1})
    back = model_from_dict(yaml.safe_load(dump_model(m, "mm", "deg")))
    q = _random_q(m, 6)
    np.testing.assert_allclose(back.fk(q), m.fk(q), atol=1e-9)
    assert back.joints == m.joints or np.allclose([j.lower for j in back.joints], m.lower)


def test_model_file_errors_name_the_field():
    doc = {"format": "station-model/1", "convention": "dh", "units": {"length": "m", "angle": "rad"},
           "joints": [{"name": "a", "limits": [1, -1], "dh": {"a": 0}}]}
    with pytest.raises(ModelFileError, match=r"joints\[0\].limits"):
        model_from_dict(doc, "f.yaml")
    doc["units"] = {"length": "m"}
    with pytest.raises(ModelFileError, match="units"):
        model_from_dict(doc, "f.yaml")


def test_ik_reaches_reachable_poses():
    m = load_model("ur5e")
    q_true = _random_q(m, 30) * 0.6
    res = m.ik(m.fk(q_true), q_true + 0.1)
    assert res.ok.mean() > 0.9
    np.testing.assert_allclose(m.fk(res.q[res.ok]), m.fk(q_true[res.ok]), atol=1e-6)


def test_encoder_scaling_roundtrip():
    m = load_model("arm6")
    e = m.joints[1].encoder
    assert e.direction == -1 and e.gear == 121
    np.testing.assert_allclose(e.to_si(e.to_counts(0.3)), 0.3)
    np.testing.assert_allclose(e.to_counts(2 * np.pi), -131072 * 121)
