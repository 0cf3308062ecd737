"""Simulated world, joint motion: trapezoid profiles respect velocity/acceleration limits, synchronised
moves finish together, velocity mode, halt, power, joint limits, time modes."""

import time

import numpy as np
import pytest
from station.mocks.world import World
from station.mocks.world import motion as mo


def _sample(world, duration, dt=0.002):
    """Sample encoder q (sim mode) over ``duration``; returns times and positions."""
    ts, qs = [world.now()], [world.encoder_q()]
    while ts[-1] < duration - 1e-12:
        world.advance(dt)
        ts.append(world.now())
        qs.append(world.encoder_q())
    return np.array(ts), np.array(qs)


def _check_limits(ts, qs, vmax, amax, dt):
    v = np.diff(qs, axis=0) / np.diff(ts)[:, None]
    a = np.diff(v, axis=0) / dt
    # finite differences of an exact trapezoid: velocity never above the limit; acceleration averaged
    # over two samples may reach the limit but not exceed it (small slack for rounding only)
    assert np.all(np.abs(v) <= vmax * (1 + 1e-9) + 1e-12)
    assert np.all(np.abs(a) <= amax * (1 + 1e-6) + 1e-9)
    return v


@pytest.mark.parametrize("x0,v0,x1", [(0.0, 0.0, 1.0), (0.0, 0.0, 0.01), (0.0, 0.8, 0.1), (0.0, 0.9, -0.5),
                                      (0.0, -0.5, 2.0), (1.0, 2.0, 1.5), (0.0, 0.3, 0.0)])
def test_track_reaches_target_within_limits(x0, v0, x1):
    vmax, amax, dt = 1.0, 4.0, 1e-3
    tr = mo.plan(0.0, x0, v0, x1, vmax, amax)
    assert tr.x_end == pytest.approx(x1, abs=1e-12)
    ts = np.arange(0.0, tr.t_end + 0.05, dt)
    st = np.array([tr.state(t) for t in ts])
    assert st[0, 0] == pytest.approx(x0, abs=1e-12) and st[0, 1] == pytest.approx(v0)
    assert st[-1, 0] == pytest.approx(x1, abs=1e-12) and st[-1, 1] == 0.0
    acc = np.diff(st[:, 1]) / dt
    assert np.all(np.abs(acc) <= amax * (1 + 1e-9))
    # from the moment it is within the limit, speed stays within it
    assert np.all(np.abs(st[ts > abs(abs(v0) - vmax) / amax + dt, 1]) <= vmax + 1e-12)
    # position is the integral of velocity (no jumps)
    assert np.max(np.abs(np.diff(st[:, 0]))) <= max(vmax, abs(v0)) * dt * 1.01


def test_rest_to_rest_duration_is_time_optimal():
    for d, vmax, amax in [(1.0, 1.0, 4.0), (0.1, 1.0, 4.0), (3.0, 0.5, 1.0)]:
        tr = mo.plan(0.0, 0.0, 0.0, d, vmax, amax)
        assert tr.t_end == pytest.approx(mo.min_time(d, vmax, amax), rel=1e-12)
    assert mo.min_time(1.0, 1.0, 4.0) == pytest.approx(1.25)  # 1/1 + 1/4
    assert mo.min_time(0.1, 1.0, 4.0) == pytest.approx(2 * np.sqrt(0.1 / 4))


def test_synchronised_move_timing_and_limits_sim_mode():
    w = World.default("ur5e", seed=3, time_mode="sim")
    q0 = w.encoder_q()
    dq = np.array([0.8, -0.3, 0.5, 0.05, -1.2, 0.0])
    speed = 1.0  # rad/s cap on every joint
    w.command_q(q0 + dq, speed=speed)
    vmax = np.minimum(speed, np.array([j.max_velocity for j in w.truth.joints]))
    amax = np.array([j.max_acceleration for j in w.truth.joints])
    expected = max(mo.min_time(d, v, a) for d, v, a in zip(dq, vmax, amax, strict=True))
    dt = 0.002
    ts, qs = _sample(w, expected + 0.1, dt)
    v = _check_limits(ts, qs, vmax, amax, dt)
    moving = np.any(np.abs(v) > 1e-9, axis=1)
    t_done = ts[1:][moving][-1]
    assert t_done == pytest.approx(expected, abs=dt)
    # straight line in joint space: all joints finish together, at the target
    np.testing.assert_allclose(qs[-1], q0 + dq, atol=1e-12)
    frac = (qs - q0) / np.where(dq == 0, 1, dq)
    for k in (0, 1, 2, 4):
        np.testing.assert_allclose(frac[:, k], frac[:, 4], atol=1e-9)
    assert not w.is_moving()


def test_instant_mode_completes_at_once():
    w = World.default("omx", seed=1)
    q1 = np.array([0.3, -0.2, 0.4, 0.1])
    w.command_q(q1)
    assert not w.is_moving()
    np.testing.assert_allclose(w.encoder_q(), q1)


def test_new_goal_while_moving_has_no_velocity_jump():
    w = World.default("omx", seed=1, time_mode="sim")
    w.command_q([1.0, 0, 0, 0])
    w.advance(0.4)
    v_before = w.encoder_qd().copy()
    w.command_q([-0.5, 0, 0, 0])
    np.testing.assert_allclose(w.encoder_qd(), v_before)
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), [-0.5, 0, 0, 0], atol=1e-12)


def test_joint_limits_clamp_and_report():
    w = World.default("omx", seed=1)
    hi = w.upper
    used = w.command_q(hi + 0.5)
    np.testing.assert_allclose(used, hi)
    np.testing.assert_allclose(w.encoder_q(), hi)
    assert any("clamped" in msg for _, msg in w.events)
    with pytest.raises(ValueError, match="4 joint values"):
        w.command_q([0.0, 0.0])
    with pytest.raises(ValueError, match="not finite"):
        w.command_q([0.0, np.nan, 0.0, 0.0])


def test_velocity_mode_and_halt_respect_acceleration_and_limits():
    w = World.default("omx", seed=1, time_mode="sim")
    amax = np.array([j.max_acceleration for j in w.truth.joints])
    vmax = np.array([j.max_velocity for j in w.truth.joints])
    w.command_qd([0.5, -0.2, 0.0, 10.0])  # j4 above its velocity limit: capped
    dt = 0.002
    ts, qs = _sample(w, 0.5, dt)
    _check_limits(ts, qs, vmax, amax, dt)
    np.testing.assert_allclose(w.encoder_qd(), [0.5, -0.2, 0.0, vmax[3]])
    w.halt()
    t_stop = np.max(np.abs(w.encoder_qd()) / amax)
    ts2, qs2 = _sample(w, w.now() + t_stop + 0.01, dt)
    _check_limits(ts2, qs2, vmax, amax, dt)
    assert not w.is_moving()
    # velocity mode runs into the joint limit and stops there, decelerating in time
    w.command_qd([vmax[0], 0, 0, 0])
    w.run_until_idle()
    assert w.encoder_q()[0] == pytest.approx(w.upper[0], abs=1e-12)
    assert not w.is_moving()


def test_disabled_joints_brake_and_ignore_commands():
    w = World.default("omx", seed=1, time_mode="sim")
    w.command_q([1.0, 0.5, 0, 0])
    w.advance(0.2)
    w.set_enabled(False, 1)
    q_brake = w.encoder_q()[1]
    w.run_until_idle()
    q = w.encoder_q()
    assert q[0] == pytest.approx(1.0) and q[1] == pytest.approx(q_brake)
    w.command_q([0.0, 0.0, 0.2, 0.0])
    w.run_until_idle()
    q = w.encoder_q()
    assert q[1] == pytest.approx(q_brake) and q[2] == pytest.approx(0.2)
    assert list(w.enabled()) == [True, False, True, True]
    w.set_enabled(True)
    w.command_q([0.0, 0.0, 0.0, 0.0])
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), 0.0, atol=1e-12)


def test_realtime_mode_follows_scaled_wall_clock():
    w = World.default("omx", seed=1, time_mode="realtime", time_scale=20.0)
    d = 1.0
    amax, vmax = w.truth.joints[0].max_acceleration, w.truth.joints[0].max_velocity
    expected = mo.min_time(d, vmax, amax) / 20.0  # wall seconds
    t0 = time.monotonic()
    w.command_q([d, 0, 0, 0])
    assert w.is_moving()
    while w.is_moving() and time.monotonic() - t0 < 5:
        time.sleep(0.001)
    wall = time.monotonic() - t0
    assert wall == pytest.approx(expected, abs=0.02)
    assert w.encoder_q()[0] == pytest.approx(d, abs=1e-12)
    with pytest.raises(RuntimeError):
        w.advance(0.1)


def test_random_tracks_are_continuous_and_end_on_target():
    rng = np.random.default_rng(5)
    for _ in range(300):
        vmax, amax = rng.uniform(0.1, 3.0), rng.uniform(0.5, 20.0)
        x0, x1 = rng.uniform(-2, 2, 2)
        v0 = rng.uniform(-1.5, 1.5) * vmax
        tr = mo.plan(0.0, x0, v0, x1, vmax, amax)
        assert tr.x_end == pytest.approx(x1, abs=1e-12)
        assert all(d >= 0 and abs(a) <= amax * (1 + 1e-12) for d, a in tr.phases)
        # velocity continuous at every phase boundary and zero at the end
        t, v = 0.0, v0
        for d, a in tr.phases:
            t += d
            v += a * d
            assert tr.state(t - 1e-9)[1] == pytest.approx(v, abs=amax * 2e-9 + 1e-9)
        assert abs(v) < 1e-9
        # never faster than max(|v0|, vmax)
        ts = np.linspace(0, tr.t_end, 200)
        assert max(abs(tr.state(x)[1]) for x in ts) <= max(abs(v0), vmax) + 1e-9
