"""Gravity compliance: torques against the potential energy of an independent URDF evaluator, FK with the
deflection, exact Jacobians, model files, the simulated world's deflection (its own, exact computation)
against the model's first-order one, and recovery of the world's compliance from noisy tip positions."""

import math

import numpy as np
import pytest
import urdf_robots as robots
import yourdfpy
from clirunner import station_proc

from station.kinematics import ModelFileError, load_model, model_from_dict
from station.kinematics.modelfile import dump_model
from station.kinematics.se3 import orientation_error

G = np.array([0.0, 0.0, -9.81])
ARM7_C = {"compliance.j2": 4e-5, "compliance.j4": 6e-5, "compliance.j6": 1.5e-4}  # rad per N m


@pytest.fixture(scope="module")
def arm7(tmp_path_factory):
    path = robots.write(tmp_path_factory.mktemp("arm7"), "arm7")
    return path, load_model(path, tip_link="ball"), yourdfpy.URDF.load(str(path), load_meshes=False)


def _q(m, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(m.lower, -math.pi), np.minimum(m.upper, math.pi)
    return lo + (hi - lo) * rng.random((n, m.n_joints))


def _urdf_potential(u, names, q):
    """V = -sum m g . p over every link's <inertial>, from yourdfpy's link transforms (fingers at zero)."""
    u.update_cfg(dict.fromkeys(u.actuated_joint_names, 0.0) | dict(zip(names, q, strict=True)))
    V = 0.0
    for link in u.robot.links:
        if link.inertial is None or link.inertial.mass is None:
            continue
        W = u.get_transform(link.name, u.base_link) @ link.inertial.origin
        V -= link.inertial.mass * (G @ W[:3, 3])
    return V


def _urdf_torque(u, names, q, h=1e-5):
    E = np.eye(len(q)) * h
    return np.array([-(_urdf_potential(u, names, q + e) - _urdf_potential(u, names, q - e)) / (2 * h) for e in E])


def test_gravity_torque_is_minus_the_gradient_of_the_urdf_potential_energy(arm7):
    _, m, u = arm7
    names = [j.name for j in m.joints]
    q = _q(m, 6, 1)
    tau = m.gravity_torque(q)
    for qi, ti in zip(q, tau, strict=True):
        # FD of the energy: truncation h^2 V''' ~ 1e-9 N m, rounding ~ 1e-16 * 100 J / 1e-5 = 1e-9 N m
        np.testing.assert_allclose(ti, _urdf_torque(u, names, qi), atol=1e-7)
    assert np.abs(tau).max() > 5.0  # a real load, not a test of zeros


def test_fk_with_compliance_against_the_urdf_at_deflected_joints(arm7):
    _, m, u = arm7
    names = [j.name for j in m.joints]
    mc = m.with_params(ARM7_C)
    c = np.array([ARM7_C.get(f"compliance.j{i + 1}", 0.0) for i in range(7)])
    moved = 0.0
    for q in _q(mc, 5, 2):
        theta = q + c * _urdf_torque(u, names, q)  # first order: torque at the undeflected joints
        u.update_cfg(dict.fromkeys(u.actuated_joint_names, 0.0) | dict(zip(names, theta, strict=True)))
        W = u.get_transform("ball", u.base_link)
        T = mc.fk(q)
        np.testing.assert_allclose(T[:3, 3], W[:3, 3], atol=1e-9)
        np.testing.assert_allclose(T[:3, :3], W[:3, :3], atol=1e-9)
        moved = max(moved, np.linalg.norm(T[:3, 3] - m.fk(q)[:3, 3]))
    assert moved > 1e-4  # the deflection is there (> 0.1 mm)


def _pose_vec(T, T0):
    return np.concatenate([T[:, :3, 3], orientation_error(T[:, :3, :3], T0[:, :3, :3])], axis=1)


def test_jacobians_with_compliance_match_finite_differences(arm7):
    _, m, _ = arm7
    mc = m.with_payload(1.2, (0.01, 0.0, 0.02)).with_params(ARM7_C)
    q = _q(mc, 4, 3)
    p = mc.params.copy()
    T0, Jq, Jp = mc.jacobians(q, p)
    h = 1e-6
    num_p = np.stack([(_pose_vec(mc.fk(q, p + h * e), T0) - _pose_vec(mc.fk(q, p - h * e), T0)) / (2 * h)
                      for e in np.eye(len(p))], axis=-1)
    np.testing.assert_allclose(Jp, num_p, atol=1e-7)
    cols = [mc.index(n) for n in ARM7_C]
    assert np.abs(Jp[:, :3, cols]).max() > 1.0  # m per (rad per N m): a compliance column is not empty
    for i in range(len(q)):
        num_q = np.stack([(_pose_vec(mc.fk(q[i] + h * e)[None], T0[i:i + 1])
                           - _pose_vec(mc.fk(q[i] - h * e)[None], T0[i:i + 1]))[0] / (2 * h)
                          for e in np.eye(7)], axis=-1)
        np.testing.assert_allclose(Jq[i], num_q, atol=1e-7)
    # the gravity stiffness is in Jq: the rigid joint Jacobian differs by more than the FD tolerance
    _, Jq_rigid, _ = m.jacobians(q + mc.deflection(q))
    assert np.abs(Jq - Jq_rigid).max() > 1e-5


def test_compliance_parameters_exist_with_a_load_and_the_group_skips_unloadable_joints(arm7, tmp_path):
    _, m, _ = arm7
    assert [n for n in m.param_names if n.startswith("compliance.")] == [f"compliance.j{i}" for i in range(1, 8)]
    assert m.select("compliance") == [f"compliance.j{i}" for i in range(2, 8)]  # joint 1 is vertical
    ur = load_model("ur5e")
    assert not any(n.startswith("compliance.") for n in ur.param_names)  # weightless: nothing to load them
    with pytest.raises(KeyError, match="has no link masses and no payload"):
        ur.select("offsets,compliance")
    loaded = ur.with_payload(2.0)
    assert loaded.select("compliance") == [f"compliance.j{i}" for i in range(2, 7)]
    assert loaded.param_names[: len(ur.param_names)] == ur.param_names  # appended: the rest keeps its index
    rail = load_model(robots.write(tmp_path, "rail_scara"))
    assert all(rail.joints[int(n[-1]) - 1].revolute for n in rail.param_names if n.startswith("compliance."))
    # gravity torque at the tool with the payload only, against the joint Jacobian's transpose
    q = _q(loaded, 5, 4)
    _, Jq, _ = ur.jacobians(q)
    np.testing.assert_allclose(loaded.gravity_torque(q), np.einsum("nri,r->ni", Jq[:, :3], 2.0 * G), atol=1e-12)


MODEL_DOC = {
    "format": "station-model/1", "name": "arm3", "convention": "dh", "units": {"length": "mm", "angle": "deg"},
    "joints": [
        {"name": "a", "limits": [-170, 170], "dh": {"a": 0, "d": 300, "alpha": 90}, "mass": 5.0, "com": [0, -20, 0]},
        {"name": "b", "limits": [-120, 120], "dh": {"a": 400, "d": 0, "alpha": 0}, "mass": 4.0, "com": [-200, 0, 30],
         "compliance": 0.003},
        {"name": "c", "limits": [-150, 150], "dh": {"a": 300, "d": 0, "alpha": 0}, "mass": 2.0, "com": [-150, 0, 0],
         "compliance": 0.005},
    ],
    "payload": {"mass": 1.5, "com": [0, 0, 20]}, "gravity": [0, 0, -9.81],
}


def test_model_file_masses_payload_and_compliance_in_stated_units():
    m = model_from_dict(MODEL_DOC, "arm3.yaml")
    assert m.param("compliance.j2") == pytest.approx(math.radians(0.003))  # deg per N m -> rad per N m
    assert m.load.link_mass(2) == (4.0, pytest.approx(np.array([-0.2, 0, 0.03])))
    assert m.load.payload[0] == 1.5 and m.load.payload[1] == pytest.approx(np.array([0, 0, 0.02]))
    q = _q(m, 6, 5)
    back = model_from_dict(__import__("yaml").safe_load(dump_model(m, "m", "rad")), "again.yaml")
    np.testing.assert_allclose(back.fk(q), m.fk(q), atol=1e-12)
    np.testing.assert_allclose(back.gravity_torque(q), m.gravity_torque(q), atol=1e-9)
    rigid = m.with_params({"compliance.j2": 0.0, "compliance.j3": 0.0})
    assert np.linalg.norm(m.position(q) - rigid.position(q), axis=1).max() > 1e-3


@pytest.mark.parametrize("change, message", [
    (lambda d: d["joints"][1].update(mass=-1), r"joints\[1\].mass: a mass cannot be negative"),
    (lambda d: d["joints"][0].pop("mass"), r"joints\[0\].com: given without a mass"),
    (lambda d: d["joints"][2].update(type="prismatic"), r"joints\[2\].compliance: only revolute"),
    (lambda d: d.update(payload={"kg": 1}), "payload: expected"),
    (lambda d: d.update(gravity=[0, -9.81]), r"gravity: expected \[x, y, z\]"),
    (lambda d: d["joints"][1].update(com=[0, 0]), r"joints\[1\].com: expected"),
    (lambda d: d["units"].update(mass="lb"), "units.mass: only kg"),
])
def test_model_file_mass_errors_are_one_line(change, message):
    doc = __import__("copy").deepcopy(MODEL_DOC)
    change(doc)
    with pytest.raises(ModelFileError, match=message) as e:
        model_from_dict(doc, "arm3.yaml")
    assert "\n" not in str(e.value) and str(e.value).startswith("arm3.yaml: ")


def _world(model, **joints):
    from station.mocks.world import World

    return World.default(model, errors={"explicit": {}, "random": {}}, joints=joints, cell={"points": []})


def _second_order_bound(m, q):
    """|exact - first-order| deflection <= |C dtau/dq| |C tau| (and the world evaluates tau on the deflected
    joints): a bound from the model's own gravity stiffness, twice for safety."""
    js, ps = m.compliance_index
    tau, dtau = m.gravity_torque(q, derivative=True)
    c = np.zeros(m.n_joints)
    c[js] = m.params[ps]
    K = np.abs(c[None, :, None] * dtau).sum(axis=2).max()
    return 2 * K * np.abs(c * tau).max() + 1e-12


UR5E_MASSES = {k + 1: (m, np.array(c)) for k, (m, c) in enumerate(robots.UR5E_MASS)}
UR5E_C = {"j2": 2e-5, "j3": 3e-5, "j4": 8e-5, "j5": 6e-5}


def test_world_deflection_matches_the_model_with_the_same_masses():
    """World file: UR5e link masses (joints.masses), a payload with its centre off the tool, compliance;
    the world computes its own exact fixed point from the potential energy."""
    joints = {"masses": {f"j{k}": {"mass": mm, "com": list(c)} for k, (mm, c) in UR5E_MASSES.items()},
              "payload": {"mass": 2.5, "com": [0.0, 0.02, 0.05]}, "compliance": UR5E_C}
    w = _world("ur5e", **joints)
    m = (load_model("ur5e").with_masses(UR5E_MASSES).with_payload(2.5, (0.0, 0.02, 0.05))
         .with_params({f"compliance.{j}": c for j, c in UR5E_C.items()}))
    assert {k: v for k, v in w.hidden().items() if k.startswith("compliance.")} == {
        f"compliance.{j}": c for j, c in UR5E_C.items()}
    worst = 0.0
    for q in _q(m, 8, 6):
        w.command_q(q)
        d_world = w.joint_q() - w.encoder_q()
        d_model = m.deflection(q)[0]
        bound = _second_order_bound(m, q[None])
        assert np.abs(d_world - d_model).max() <= bound
        assert np.abs(d_model).max() > 1e-4  # a real deflection (> 0.006 deg)
        np.testing.assert_allclose(w.tip_true(), m.position(q), atol=2 * bound)  # reach < 1.2 m
        worst = max(worst, float(np.abs(d_world - d_model).max()))
    assert worst < 5e-6  # first order is enough: < 5 urad (5 um at 1 m) from the exact deflection


def test_world_takes_link_masses_from_a_urdf_model(arm7):
    path, m, _ = arm7
    from station.mocks.world import World

    doc = {"format": "station-world/1", "units": {"length": "m", "angle": "rad"},
           "robot": {"model": str(path), "tip_link": "ball"}, "cell": {"points": []},
           "joints": {"compliance": {k.split(".")[1]: v for k, v in ARM7_C.items()}, "payload": 0.8}}
    w = World.from_dict(doc)
    mc = m.with_payload(0.8).with_params(ARM7_C)
    for q in _q(mc, 5, 7):
        w.command_q(q)
        assert np.abs((w.joint_q() - q) - mc.deflection(q)[0]).max() <= _second_order_bound(mc, q[None])
    assert "mass of link 4" in w.truth_report() and "payload 0.8 kg" in w.truth_report()


def test_compliance_is_recovered_from_noisy_tip_positions_within_its_sigma():
    """Tip positions measured with 20 um noise at 40 poses of a compliant UR5e carrying 3 kg 10 cm beyond the
    flange (the world's exact deflection); joint offsets and compliance identified by Gauss-Newton on the
    model's analytic Jacobian. Over 30 noise draws the errors scaled by their sigma have unit RMS (coverage),
    each below 4, and every sigma is below a tenth of its value (the data determine them)."""
    comp = {"j2": 2e-5, "j3": 3e-5, "j4": 8e-5}
    joints = {"masses": {f"j{k}": {"mass": mm, "com": list(c)} for k, (mm, c) in UR5E_MASSES.items()},
              "payload": {"mass": 3.0, "com": [0, 0, 0.1]}, "compliance": comp}
    w = _world("ur5e", **joints)
    truth = {f"compliance.{j}": c for j, c in comp.items()}
    model = load_model("ur5e").with_masses(UR5E_MASSES).with_payload(3.0, (0, 0, 0.1))
    names = ["offset.j2", "offset.j3", "offset.j4", *truth]
    q = _q(model, 40, 8)
    q[:, 1] = np.random.default_rng(9).uniform(-2.8, -0.3, len(q))  # shoulder above the table, loaded
    tips = []
    for qi in q:
        w.command_q(qi)
        tips.append(w.tip_true())
    tips = np.array(tips)
    sigma_m = 20e-6
    idx = [model.index(n) for n in names]
    z = []
    rng = np.random.default_rng(10)
    for _ in range(30):
        meas = tips + rng.normal(0, sigma_m, tips.shape)
        p = model.params.copy()
        for _it in range(4):
            T, _, Jp = model.jacobians(q, p)
            J = Jp[:, :3, idx].reshape(-1, len(idx))
            r = (meas - T[:, :3, 3]).ravel()
            p[idx] += np.linalg.lstsq(J, r, rcond=None)[0]
        cov = np.linalg.inv(J.T @ J) * sigma_m ** 2
        est = dict(zip(names, p[idx], strict=True))
        std = dict(zip(names, np.sqrt(np.diag(cov)), strict=True))
        z.append([(est[n] - truth[n]) / std[n] for n in truth])
        assert all(std[n] < 0.1 * truth[n] for n in truth)  # the data do determine them
    z = np.array(z)
    assert np.abs(z).max() < 4.0
    assert 0.6 < np.sqrt((z ** 2).mean()) < 1.5


def test_cli_payload_option(tmp_path):
    from station.cli.model_options import parse_payload

    assert parse_payload("0.1kg") == (0.1, (0.0, 0.0, 0.0))
    assert parse_payload("250g")[0] == pytest.approx(0.25)
    assert parse_payload("0.5kg@0,0,30mm")[1] == pytest.approx((0.0, 0.0, 0.03))
    joints = tmp_path / "q.csv"
    joints.write_text("q1,q2,q3,q4,q5,q6\n0.1,-1.2,1.4,-1.5,-1.6,0.2\n")
    r = station_proc("model", "show", "ur5e", "--payload", "0.5kg@0,0,30mm")
    assert r.code == 0 and "compliance.j2" in r.out and "mass: 0.5" in r.out
    for bad, msg in (("5", "expected a mass with its unit"), ("-1kg", "a mass is a finite number"),
                     ("1kg@1,2", "--payload")):
        r = station_proc("fk", "--model", "ur5e", "--joints", joints, "--payload", bad)
        assert r.code == 2 and r.err.startswith("station: error: --payload") and msg in r.err, r.err
        assert len(r.err.strip().splitlines()) == 1
    samples = tmp_path / "s.csv"
    samples.write_text("q1,q2,q3,q4,q5,q6,point\n" + "".join(f"0.1,-1.2,1.4,-1.5,-1.6,{0.1 * i},A\n"
                                                             for i in range(8)))
    r = station_proc("solve", "--model", "ur5e", "--samples", samples, "--identify", "offsets,compliance")
    assert r.code == 2 and "has no link masses and no payload" in r.err
    assert len(r.err.strip().splitlines()) == 1
