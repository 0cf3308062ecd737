"""The technician's approach aids without a robot: the proximity cue, the planned "go near" and which points
guidance may send the technician to (station.tui.approach), forced samples in the live solve and the verdict
(station.tui.livesolve, station.tui.guidance). Ground truth is computed here independently: forward kinematics
sampled along every joint path (tool speed, distance to the point, keep-out by the link capsules)."""

from __future__ import annotations

import numpy as np
import pytest

from station.engine import events as ev
from station.kinematics import load_model
from station.kinematics.collision import Checker, KeepOut, keep_out_from_dict
from station.robot.errors import LimitError
from station.tui import guidance as gd
from station.tui.approach import NEAR_CLEAR, NEAR_CONE, NEAR_STANDOFF, Target, plan_near, proximity, reach_problem
from station.tui.livesolve import SolveState, live_solve

START = np.array([0.1, -1.45, 1.6, -1.72, -1.5708, 0.2])
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def ur5e():
    return load_model("ur5e")


def _ik(model, xyz):
    """Tool at ``xyz`` pointing straight down, elbow up, all links clear (the model's own IK, seeded with the
    start posture turned to face +x)."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = xyz
    r = model.ik(T, START + [np.pi, 0, 0, 0, 0, 0])
    assert r.ok[0] and Checker(model, KeepOut.default()).clear(r.q)[0]
    return r.q[0]


def _samples(model, path, n=2000):
    """Tool positions and times along straight joint segments at the plan's lead-joint speeds."""
    pts, ts, t0 = [], [], 0.0
    for (a, b), v in path:
        s = np.linspace(0.0, 1.0, n)[:, None]
        dur = float(np.max(np.abs(b - a))) / v
        pts.append(model.position(a + s * (b - a)))
        ts.append(t0 + s[:, 0] * dur)
        t0 += dur
    return np.concatenate(pts), np.concatenate(ts)


def test_proximity_is_the_tool_to_point_vector_in_the_jog_frame(ur5e):
    T = ur5e.fk(START)
    in_tool = np.array([0.003, -0.004, 0.012])  # the point as seen along the tool's own axes
    target = Target("A", "socket", T[:3, 3] + T[:3, :3] @ in_tool, UP, radius=0.008)
    base, tool = proximity(T, target, "base"), proximity(T, target, "tool")
    np.testing.assert_allclose(tool.delta, in_tool, atol=1e-12)  # the move along the tool axes
    d = T[:3, :3] @ in_tool
    np.testing.assert_allclose(base.delta, d, atol=1e-12)  # the same move along the base axes
    assert base.distance == pytest.approx(np.linalg.norm(in_tool))
    assert base.above == pytest.approx(-d[2]) and base.lateral == pytest.approx(np.hypot(d[0], d[1]))
    assert base.within == (np.linalg.norm(in_tool) <= 0.008)
    far = Target("B", "socket", T[:3, 3] + [0.0, 0.0, -0.009], UP, radius=0.008)
    assert proximity(T, far).above == pytest.approx(0.009) and not proximity(T, far).within


def test_go_near_ends_at_the_standoff_clear_and_within_the_speed_cap(ur5e):
    socket = Target("A", "socket", np.array([0.45, 0.0, 0.05]), UP, 0.008)
    cap = 0.25
    keep_out = KeepOut.default()
    plan = plan_near(ur5e, keep_out, START, socket, cap)
    T = ur5e.fk(plan.path[-1])
    np.testing.assert_allclose(T[:3, 3], socket.position + UP * NEAR_STANDOFF, atol=1e-6)
    assert T[:3, 2] @ -UP >= np.cos(NEAR_CONE) - 1e-9  # the tool points into the socket's cone
    segments = list(zip([START, *plan.path[:-1]], plan.path, strict=True))
    checker = Checker(ur5e, keep_out)
    assert all(checker.path_hit(a, b) is None for a, b in segments)  # every link clear on every segment
    pts, ts = _samples(ur5e, list(zip(segments, plan.speeds, strict=True)))
    speed = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.maximum(np.diff(ts), 1e-12)
    assert speed.max() <= cap * (1 + 1e-3), speed.max()  # manual-jog cap at the tool, everywhere on the path
    assert speed.max() >= 0.5 * cap  # and not needlessly slow
    assert np.linalg.norm(pts - socket.position, axis=1).min() >= NEAR_STANDOFF * NEAR_CLEAR - 1e-4
    assert plan.seconds == pytest.approx(ts[-1], rel=1e-9)
    # at a lower override the same path, slower
    slow = plan_near(ur5e, keep_out, START, socket, 0.025)
    assert slow.seconds == pytest.approx(plan.seconds * 10, rel=0.05)
    # never above 250 mm/s, whatever is asked
    assert plan_near(ur5e, keep_out, START, socket, 1.0).cap == pytest.approx(0.25)


def test_go_near_comes_in_along_the_approach_instead_of_sweeping_across_the_point(ur5e):
    needle = Target("N", "needle", np.array([0.45, 0.0, 0.30]), UP, 5e-5)
    q0 = _ik(ur5e, [0.35, 0.0, 0.20])  # beside and below the needle: the straight path would pass its tip
    plan = plan_near(ur5e, KeepOut.default(), q0, needle, 0.1)
    assert any("enters along the approach" in n for n in plan.notes), plan.notes
    pts, _ = _samples(ur5e, [((a, b), v) for a, b, v in zip([q0, *plan.path[:-1]], plan.path, plan.speeds,
                                                             strict=True)])
    assert np.linalg.norm(pts - needle.position, axis=1).min() >= NEAR_STANDOFF * NEAR_CLEAR - 1e-4
    # right below the needle there is no way round it: refused, nothing moves
    with pytest.raises(LimitError, match="sweep the tool across the point"):
        plan_near(ur5e, KeepOut.default(), _ik(ur5e, [0.45, 0.0, 0.22]), needle, 0.1)


def test_go_near_avoids_a_keep_out_or_names_it(ur5e):
    socket = Target("A", "socket", np.array([0.45, 0.0, 0.05]), UP, 0.008)
    straight = plan_near(ur5e, KeepOut.default(), START, socket, 0.25)
    assert len(straight.path) == 1
    # a box round the middle of that straight path
    mid = ur5e.position((START + 0.5 * (straight.path[-1] - START))[None])[0]
    keep_out = keep_out_from_dict({"keep_out": [{"name": "mast", "box": {"center": mid.tolist(),
                                                                         "size": [0.12, 0.12, 0.12]}}]},
                                  "cell", 1.0, 1.0)
    checker = Checker(ur5e, keep_out)
    assert checker.path_hit(START, straight.path[-1]) is not None
    try:
        plan = plan_near(ur5e, keep_out, START, socket, 0.25)
    except LimitError as e:
        assert "mast" in str(e)
        return
    assert len(plan.path) > 1 and any("via" in n for n in plan.notes)
    segments = zip([START, *plan.path[:-1]], plan.path, strict=True)
    assert all(checker.path_hit(a, b) is None for a, b in segments)


def test_points_out_of_reach_are_refused_and_reported(ur5e):
    far = Target("F", "socket", np.array([2.0, 0.0, 0.5]), UP, 0.008)
    with pytest.raises(LimitError, match="cannot put the tool"):
        plan_near(ur5e, KeepOut.default(), START, far, 0.25)
    assert "out of reach" in reach_problem(ur5e, far, Checker(ur5e, KeepOut.default()), START)
    near = Target("A", "socket", np.array([0.45, 0.0, 0.05]), UP, 0.008)
    assert reach_problem(ur5e, near, Checker(ur5e, KeepOut.default()), START) is None


def test_guidance_never_sends_the_technician_to_a_blocked_point():
    labels = ["A", "B", "N"]
    per = {"A": 2, "B": 0, "N": 1}
    assert gd.next_point(labels, per) == "B"
    assert gd.next_point(labels, per, {"B": "socket: no compliant mode"}) == "N"
    assert gd.next_point(labels, per, {lb: "x" for lb in labels}) is None


def _sample(seq, q, point="A", forced=False, touch=None):
    s = ev.Sample(point=point, q=list(q), raw=list(q), raw_unit="rad", t_read=0.0, t_device=None, pose=seq,
                  status={"touch": False if forced else touch, "forced": forced})
    s.seq = seq
    return s


def test_a_solve_on_forced_samples_is_never_shown_as_identified(ur5e):
    rng = np.random.default_rng(4)
    target = np.array([0.45, 0.0, 0.05])
    qs = []
    while len(qs) < 12:  # touches of one point from spread poses (nominal model: a perfect fit)
        r = ur5e.ik(target, START + rng.uniform(-0.4, 0.4, 6), position_only=True)
        if r.ok[0]:
            qs.append(r.q[0])
    clean = [_sample(i, q) for i, q in enumerate(qs)]
    st = live_solve(ur5e, clean, "offsets", "unknown")
    assert st.status == "ok" and st.forced == 0 and st.identified_ok and st.warning is None
    assert max(st.sample_residuals.values()) < 1e-6 and len(st.sample_residuals) == 12
    mixed = [_sample(i, q, forced=i < 3) for i, q in enumerate(qs)]
    st = live_solve(ur5e, mixed, "offsets", "unknown")
    assert st.forced == 3 and not st.identified_ok
    assert "3 of 12 samples forced" in st.warning and "not identified" in st.warning
    every = live_solve(ur5e, [_sample(i, q, forced=True) for i, q in enumerate(qs)], "offsets", "unknown")
    assert "every sample was forced" in every.warning
    assert SolveState().warning is None
    # the verdict: a forced sample fails the session whatever the limits file says about the rest
    verdict = gd.judge({}, gd.measurements(ur5e, st.result, 12, None, forced=3), None)
    assert verdict["passed"] is None  # no limits: NO LIMITS stays NO LIMITS (never a PASS either way)
    from station.engine.limits import load_limits

    table = load_limits(None).for_procedure("ur5e", "jog")
    verdict = gd.judge(table, gd.measurements(ur5e, st.result, 12, None, forced=3), None)
    forced = {m["name"]: m for m in verdict["measurements"]}["forced_samples"]
    assert verdict["passed"] is False and forced["passed"] is False and forced["value"] == 3
