"""``station.drivers.franka.press``: the seating press's direction, its joint target and the rest it waits for
(the FR3 model, no robot). The press on franka-sim itself: tests/drivers/franka/test_franka_driver.py, and the
zero_offsets (tests/e2e/test_bus_conformance.py) and two-socket runs."""

from __future__ import annotations

import numpy as np
import pytest
from station.drivers.franka import press

from station.kinematics import load_model

Q = np.array([0.1, 0.3, -0.1, -2.0, 0.05, 2.3, 0.7])  # a seating-like FR3 pose, tool pointing down


@pytest.fixture(scope="module")
def fr3():
    return load_model("fr3")


def _along(model, q, d):
    """Joints that put the tool ``d`` (m, base frame) from where it is at ``q``, orientation kept (by iteration:
    an independent route to the same pose, not the press's one-step Jacobian)."""
    target = model.fk(q)
    target[:3, 3] += d
    r = model.ik(target, q)
    assert r.ok[0]
    return r.q[0]


def test_the_press_goes_along_the_approach_the_move_made(fr3):
    down = np.array([0.01, -0.02, -1.0]) / np.linalg.norm([0.01, -0.02, -1.0])
    q_from = _along(fr3, Q, -0.03 * down)  # 30 mm back along the approach
    u, why = press.direction(fr3, q_from, Q, Q)
    assert why == "" and np.allclose(u, down, atol=1e-9)
    # the stiff move stopped short by 2 mm (the ball on the cone's rim): still the same approach to press along
    short = _along(fr3, Q, -0.002 * down)
    u2, _ = press.direction(fr3, q_from, Q, short)
    assert np.allclose(u2, down, atol=1e-9)


def test_no_press_after_a_rotation_in_place_or_a_move_that_ended_elsewhere(fr3):
    turned = Q.copy()
    turned[6] += 0.3  # joint 7 turns the flange (fr3's tool point) about its own axis: it does not travel
    u, why = press.direction(fr3, Q, turned, turned)
    assert u is None and "rotation in place" in why
    q_from = _along(fr3, Q, np.array([0, 0, 0.03]))
    stopped = _along(fr3, Q, np.array([0, 0, 0.007]))  # 7 mm short: something else stopped it
    u, why = press.direction(fr3, q_from, Q, stopped)
    assert u is None and "7.0 mm from its target" in why


def test_the_press_target_is_depth_beyond_with_the_orientation_kept(fr3):
    u = np.array([0.0, 0.6, -0.8])
    depth = 5.0 / 600.0  # 5 N at 600 N/m: 8.3 mm
    p = press.plan(fr3, Q, u, depth)
    T0, T1 = fr3.fk(Q), fr3.fk(p.q)
    assert np.allclose(p.p0, T0[:3, 3])
    # 8 mm straight to a micrometre, the orientation kept to 10 microradians
    assert np.linalg.norm(T1[:3, 3] - (T0[:3, 3] + depth * u)) < 1e-6
    R = T0[:3, :3].T @ T1[:3, :3]
    assert np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)) < 1e-5
    assert p.travel(T1[:3, 3]) == pytest.approx(depth, abs=5e-6)
    assert p.travel(T0[:3, 3] - 0.001 * u) == pytest.approx(-0.001)
    # the joint speed moves the tool at press.SPEED
    v = press.joint_speed(p, Q)
    duration = np.max(np.abs(p.q - Q)) / v
    assert np.linalg.norm(T1[:3, 3] - T0[:3, 3]) / duration == pytest.approx(press.SPEED, rel=1e-3)


def test_rest_needs_a_still_tool_and_a_steady_force():
    rng = np.random.default_rng(3)
    s = press.Settle(press_force=5.0)
    t = 0.0
    # the target still travelling: the tool moves, never rest
    for _ in range(100):
        assert not s.add(t, 0.02, 0.0)
        t += 0.004
    # the ball stopped in the cone, the force still building (the target goes on): not rest
    for k in range(50):
        assert not s.add(t, 0.0005, 0.1 * k)
        t += 0.004
    # steady at 5 N with the estimate's noise: rest after STEADY_S
    first = None
    for _ in range(100):
        if s.add(t, 0.0005, 5.0 + rng.normal(0, 0.2)) and first is None:
            first = t
        t += 0.004
    assert first is not None and s.rested
    # a jolt of the force starts the rest over
    assert not s.add(t, 0.0005, 8.0)
    assert not s.rested
