"""``station.kinematics.gravity`` (the station's analytic joint torques) against ``station.mocks.world.physics``
(the simulated world's torques: central differences of the potential energy) and against the potential energy
of a payload computed from forward kinematics alone; the world's deflection is the exact fixed point."""

from __future__ import annotations

import numpy as np
import pytest
from station.mocks.world.physics import Gravity, Rigid

from station.kinematics import load_model
from station.kinematics.gravity import make_load, payload_dict, same_payload, show_payload

HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
MASSES = {2: (8.4, np.array([0.2, 0.0, 0.14])), 3: (2.3, np.array([0.2, 0.0, 0.02]))}
PAYLOAD = (5.0, np.array([0.0, 0.01, 0.05]))


@pytest.fixture(scope="module")
def arm():
    return load_model("ur5e").with_masses(MASSES).with_payload(*PAYLOAD)


def test_analytic_torques_match_the_worlds_potential_energy(arm):
    world = Gravity(arm, MASSES, PAYLOAD, (0.0, 0.0, -9.81), np.zeros(6))
    rng = np.random.default_rng(1)
    for q in HOME + rng.uniform(-0.8, 0.8, (5, 6)):
        tau = arm.gravity_torque(q)[0]
        assert np.abs(tau - world.torque(q)).max() < 1e-5  # N m, central differences with 1e-6 rad steps
    assert abs(arm.gravity_torque(HOME)[0, 0]) < 1e-9  # joint 1 turns about the vertical: gravity cannot


def test_payload_torque_from_forward_kinematics_alone():
    m, g = 5.0, 9.81
    arm = load_model("ur5e").with_payload(m)  # at the tool point
    q = HOME
    h = 1e-6
    tau_fd = np.array([(arm.fk(q + h * e)[2, 3] - arm.fk(q - h * e)[2, 3]) / (2 * h) for e in np.eye(6)]) * -m * g
    assert np.allclose(arm.gravity_torque(q)[0], tau_fd, atol=1e-5)


def test_stiffness_is_the_derivative_of_the_torque(arm):
    q = HOME + 0.1
    tau, dtau = arm.gravity_torque(q, derivative=True)
    h = 1e-6
    fd = np.stack([(arm.gravity_torque(q + h * e)[0] - arm.gravity_torque(q - h * e)[0]) / (2 * h)
                   for e in np.eye(6)], axis=1)
    assert np.allclose(dtau[0], fd, atol=1e-5)


def test_the_worlds_deflection_balances_springs_and_gravity(arm):
    c = np.array([0, 2e-5, 1e-5, 5e-6, 0, 0])
    world = Gravity(arm, MASSES, PAYLOAD, (0.0, 0.0, -9.81), c)
    theta = world.deflect(HOME)
    assert np.abs(theta - (HOME + c * world.torque(theta))).max() < 1e-12
    assert np.abs(theta - HOME).max() > 1e-5  # it does bend
    assert Rigid().deflect(HOME) is HOME and not Gravity(arm, {}, (0.0, np.zeros(3)), (0, 0, -9.81), c).active


def test_loads_and_payload_records():
    assert make_load(6, np.zeros(3)) is None  # weightless
    with pytest.raises(ValueError, match="the links are 1..6"):
        make_load(6, np.zeros(3), {8: (1.0, np.zeros(3))})
    with pytest.raises(ValueError, match="need a finite mass >= 0"):
        make_load(6, np.zeros(3), {2: (-1.0, np.zeros(3))})
    p = payload_dict(load_model("ur5e").with_payload(15.0, (0, 0, 0.03)))
    assert p["mass"] == 15.0 and p["com"] == pytest.approx([0.0, 0.0, 0.03], abs=1e-15)
    assert payload_dict(load_model("ur5e")) is None
    assert show_payload(p) == "15 kg at [0, 0, 30] mm" and show_payload(None) == "no payload"
    assert same_payload(p, {"mass": 15.0005, "com": [0.0, 0.0, 0.03005]})  # within 1 g and 0.1 mm
    assert not same_payload(p, {"mass": 15.01, "com": [0.0, 0.0, 0.03]})
    assert same_payload(None, {"mass": 0.0, "com": [1, 2, 3]}) and not same_payload(p, {"mass": 15})
