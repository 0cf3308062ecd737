"""Joints off their profiles in the simulated world: a free (unbraked, unpowered) joint falls under gravity,
a torque-commanded joint obeys its torque, a torque-limited position controller sags when its load needs more.

Ground truth is independent of the world's own dynamics: gravity torques from the station's analytic
point-mass formula (``Model.gravity_torque``, a different computation from the world's finite differences of
the potential energy), and plain physics (an unheld arm ends lower than it started)."""

import math

import numpy as np
import pytest
import urdf_robots as robots
from station.mocks.world import World
from station.mocks.world.dynamics import estimated_masses
from station.mocks.world.worldfile import WorldFileError

from station.kinematics import load_model

UR5E_MASSES = {k + 1: (m, np.array(c)) for k, (m, c) in enumerate(robots.UR5E_MASS)}
# UR5e with the upper arm horizontal: joints 2 and 3 carry the arm's weight
Q_LOADED = np.array([0.0, -0.3, 0.5, -1.2, -1.5, 0.0])


def _world(time_mode="sim", brakes=None, masses=True, **joints):
    if masses:
        joints["masses"] = {f"j{k}": {"mass": m, "com": list(c)} for k, (m, c) in UR5E_MASSES.items()}
    if brakes is not None:
        joints["brakes"] = brakes
    return World.default("ur5e", seed=1, time_mode=time_mode, start=Q_LOADED, joints=joints)


def _model():
    return load_model("ur5e").with_masses(UR5E_MASSES)


def _tool_height(w):
    """What falling lowers (m): the tool's height on the nominal geometry."""
    return float(_model().position(w.encoder_q()).reshape(-1)[2])


def test_holding_torque_matches_the_station_s_analytic_gravity_model():
    w = _world()
    truth = w.truth.with_masses(UR5E_MASSES)  # the world's true geometry, the station's torque formula
    expected = -truth.gravity_torque(Q_LOADED)[0]  # the motor holds the load: minus gravity's torque
    np.testing.assert_allclose(w.joint_torque(), expected, atol=1e-6 * np.abs(expected).max())
    np.testing.assert_allclose(w.gravity_torque(), -expected, atol=1e-6 * np.abs(expected).max())
    assert abs(expected[1]) > 10  # joint 2 really carries the arm (N m)


def test_a_braked_joint_holds_and_an_unbraked_one_falls_under_gravity():
    w = _world(brakes=["j1", "j3", "j4", "j5", "j6"])  # joint 2 has none
    z0 = _tool_height(w)
    w.set_enabled(False)
    w.advance(0.05)
    assert w.is_moving() and w.joint_moving()[1]
    w.run_until_idle(max_time=20.0)
    q = w.encoder_q()
    np.testing.assert_array_equal(np.delete(q, 1), np.delete(Q_LOADED, 1))  # the brakes held
    tau_g = _model().gravity_torque(Q_LOADED)[0][1]  # gravity on joint 2 at the start
    assert math.copysign(1, q[1] - Q_LOADED[1]) == math.copysign(1, tau_g)  # it fell the way gravity pulls
    assert _tool_height(w) < z0 - 0.05  # the tool came down
    # at rest: hanging (no torque left) or on its end stop
    tau_end = _model().gravity_torque(q)[0][1]
    assert abs(tau_end) < 0.5 or q[1] in (w.lower[1], w.upper[1])
    assert w.joint_torque()[1] == 0.0  # no power, no motor torque


def test_re_enabling_catches_a_falling_joint_where_it_is():
    w = _world(brakes="none")
    w.set_enabled(False, 1)
    w.advance(0.1)
    q_fallen = w.encoder_q()[1]
    assert abs(q_fallen - Q_LOADED[1]) > 1e-3
    w.set_enabled(True, 1)
    w.advance(1.0)
    assert w.encoder_q()[1] == pytest.approx(q_fallen, abs=1e-9) and not w.is_moving()


def test_the_world_file_says_which_joints_have_brakes_and_the_device_default_applies_only_when_it_is_silent():
    w = _world(brakes="none")
    w.default_brakes(True)  # the file said none: an emulator's default does not override it
    assert not w.brakes.any()
    w = _world()
    assert w.brakes.all()  # unsaid: every joint braked until the device says otherwise
    w.default_brakes(False)
    assert not w.brakes.any()
    with pytest.raises(WorldFileError, match="joints.brakes"):
        _world(brakes=["j9"])
    with pytest.raises(WorldFileError, match="joints.brakes"):
        _world(brakes="some")
    doc = _world(brakes=["j2"]).to_dict()
    assert World.from_dict(doc).brakes.tolist() == [False, True, False, False, False, False]


def test_torque_mode_moves_the_joint_by_its_torque_not_by_position():
    w = _world()
    hold = w.joint_torque()[1]
    w.command_torque(hold, 1)  # exactly what holding takes: the joint stays
    w.advance(0.5)
    assert abs(w.encoder_q()[1] - Q_LOADED[1]) < 1e-4
    w.command_torque(hold + 20.0, 1)  # more: it accelerates in the direction of the extra torque
    w.advance(0.2)
    assert w.encoder_q()[1] - Q_LOADED[1] > 1e-3 and w.encoder_qd()[1] > 0
    w.command_torque(0.0, 1)  # nothing: gravity takes it
    w.run_until_idle(max_time=20.0)
    w.command_q(Q_LOADED)  # a position command ends torque mode
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), Q_LOADED, atol=1e-12)


def test_a_torque_limit_below_the_load_sags_the_joint_until_the_limit_carries_it():
    w = _world()
    need = abs(w.joint_torque()[1])
    w.set_torque_limit(1.2 * need, 1)  # enough: position control holds exactly
    w.advance(0.5)
    assert w.encoder_q()[1] == Q_LOADED[1]
    w.set_torque_limit(0.6 * need, 1)  # not enough: sags until gravity's torque is down to the limit
    w.run_until_idle(max_time=30.0)
    q = w.encoder_q()
    assert abs(q[1] - Q_LOADED[1]) > 0.05
    tau = abs(w.truth.with_masses(UR5E_MASSES).gravity_torque(q)[0][1])
    assert tau == pytest.approx(0.6 * need, abs=w.dynamics_friction()[1] + 1e-6 * need)  # friction holds it
    assert abs(w.joint_torque()[1]) == pytest.approx(0.6 * need, rel=1e-6)
    w.set_torque_limit(None, 1)  # limit lifted: back to the commanded position
    w.run_until_idle(max_time=10.0)
    assert w.encoder_q()[1] == pytest.approx(Q_LOADED[1], abs=1e-6)


def test_instant_mode_completes_a_fall_at_once():
    w = _world(time_mode="instant", brakes="none")
    w.set_enabled(False, 1)
    q = w.encoder_q()
    assert abs(q[1] - Q_LOADED[1]) > 0.05 and not w.is_moving()


def test_an_arm_without_stated_masses_still_falls_with_masses_estimated_from_its_size():
    w = World.default("omx", seed=0, time_mode="instant", joints={"brakes": "none"},
                      start=[0.0, 0.6, -0.3, 0.0])
    q0 = w.encoder_q()
    w.set_enabled(False)
    assert np.abs(w.encoder_q() - q0).max() > 0.05
    m = estimated_masses(load_model("omx"))
    assert 0.3 < sum(v[0] for v in m.values()) < 1.2  # a small servo arm carries well under a kilogram
    big = estimated_masses(load_model("ur5e"))
    assert 10 < sum(v[0] for v in big.values()) < 25


def test_dynamics_constants_from_the_world_file():
    w = _world(dynamics={"damping": {"j2": 5000.0}, "friction": 1e6})
    w.set_enabled(False)  # brakes on every joint: nothing moves
    w.set_enabled(True)
    w2 = _world(brakes="none", dynamics={"friction": 1e6})  # friction beyond the load: an unbraked joint stays
    w2.set_enabled(False)
    w2.advance(0.5)
    np.testing.assert_array_equal(w2.encoder_q(), Q_LOADED)
    with pytest.raises(WorldFileError, match="joints.dynamics.inertia"):
        _world(dynamics={"inertia": 0})
    with pytest.raises(WorldFileError, match="joints.dynamics"):
        _world(dynamics={"stiffness": 1})


def test_positioning_noise_scatters_the_link_not_the_encoder():
    """noise.positioning: each move ends the link a little off where the encoder says; the same command repeated
    lands the true tip with a scatter whose joint-space sigma is the one stated."""
    sigma = 2e-4
    w = World.default("ur5e", seed=3, time_mode="instant", noise={"positioning": sigma})
    a, b = Q_LOADED, Q_LOADED + 0.2
    errs = []
    for _ in range(400):
        w.command_q(b)
        w.command_q(a)
        np.testing.assert_array_equal(w.encoder_q(), a)  # the encoder reads the commanded position
        errs.append(w.joint_q() - a)
    errs = np.array(errs)
    # 400 draws: the sample sigma is within 4 standard errors (sigma / sqrt(2 * 400)) of the stated one
    assert np.abs(errs.std(axis=0) - sigma).max() < 4 * sigma / math.sqrt(800)
    assert np.abs(errs.mean(axis=0)).max() < 4 * sigma / math.sqrt(400)
    quiet = World.default("ur5e", seed=3, time_mode="instant")
    quiet.command_q(b)
    quiet.command_q(a)
    np.testing.assert_allclose(quiet.joint_q(), a, atol=1e-12)
