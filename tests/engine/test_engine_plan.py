"""Pose plans: reachable within limits, nominal tip on the point, approach backed off, enough poses for the
unknowns, ordered for short motion; procedures listed or generated."""

import numpy as np
import pytest

from station.engine.cell import RefPoint
from station.engine.plan import (
    PlanError,
    PosePlan,
    generate_plan,
    generate_rotation_plan,
    order_for_short_motion,
    plan_from_joints,
)
from station.kinematics import load_model

CASES = [("ur5e", [0.45, 0.0, 0.05], [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]),
         ("arm6", [0.40, 0.0, 0.70], [0.0, -0.5, 0.5, 0.0, 0.0, 0.0]),
         ("omx", [0.20, 0.0, 0.03], [0.0, 0.0, 0.0, 0.0]),
         ("scara", [0.40, 0.20, 0.20], [0.3, 0.8, 0.05, 0.0])]


@pytest.mark.parametrize("model, pos, start", CASES)
def test_generated_plan_touches_the_point_inside_limits(model, pos, start):
    m = load_model(model)
    pt = RefPoint("A", "socket", np.array(pos), np.array([0.0, 0.0, 1.0]))
    plan = generate_plan(m, [pt], start, identify="offsets", n_holdout=4)
    q = np.array([p.q for p in plan.poses])
    qa = np.array([p.approach_q for p in plan.poses])
    assert len(plan.of_set("fit")) == 20 and len(plan.of_set("holdout")) == 4
    assert m.within_limits(q).all() and m.within_limits(qa).all()
    assert np.abs(m.position(q) - pt.position).max() < 1e-6
    assert np.abs(m.position(qa) - (pt.position + [0, 0, 0.03])).max() < 1e-6
    if m.n_joints >= 6:  # tool axis inside the 35 deg cone around "down"
        z = m.fk(q)[:, :3, 2]
        assert np.all(z @ np.array([0, 0, -1.0]) >= np.cos(np.radians(35)) - 1e-9)
    # distinct poses, round trip through the journal form
    assert len({tuple(np.round(x, 6)) for x in q}) == len(q)
    again = PosePlan.from_dict(plan.to_dict())
    assert [p.q for p in again.poses] == [p.q for p in plan.poses]


def test_plan_is_deterministic_for_a_seed_and_ordered_short():
    m = load_model("ur5e")
    pt = RefPoint("A", "socket", np.array([0.45, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))
    start = np.array(CASES[0][2])
    a = generate_plan(m, [pt], start, seed=3)
    b = generate_plan(m, [pt], start, seed=3)
    assert [p.q for p in a.poses] == [p.q for p in b.poses]
    q = np.array([p.q for p in a.poses])

    def tour_time(order):
        pts = [start] + [q[i] for i in order]
        return sum(np.max(np.abs(y - x) / m.max_velocity) for x, y in zip(pts, pts[1:], strict=False))

    rng = np.random.default_rng(0)
    random_orders = [tour_time(rng.permutation(len(q))) for _ in range(20)]
    assert tour_time(range(len(q))) < min(random_orders)  # the plan's own order
    assert order_for_short_motion(m, q[:1], start) == [0]


def test_unreachable_point_and_too_few_poses_are_plan_errors():
    m = load_model("ur5e")
    far = RefPoint("A", "socket", np.array([3.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(PlanError, match="not reachable"):
        generate_plan(m, [far], np.zeros(6))
    ok = RefPoint("A", "socket", np.array([0.45, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(PlanError, match="equations for"):
        generate_plan(m, [ok], np.array(CASES[0][2]), n_fit=2)


def test_rotation_plan_spreads_the_rotary_axis_and_keeps_the_tip():
    m = load_model("scara")
    pt = RefPoint("A", "socket", np.array([0.40, 0.20, 0.20]), np.array([0.0, 0.0, 1.0]))
    plan = generate_rotation_plan(m, pt, CASES[3][2], n_fit=8, n_holdout=2)
    q = np.array([p.q for p in plan.poses])
    assert np.ptp(q[:, 3]) > np.radians(250)
    assert np.abs(m.position(q) - pt.position).max() < 1e-6
    assert len(plan.of_set("holdout")) == 2


def test_listed_plan_checks_limits():
    m = load_model("ur5e")
    pts = {"A": RefPoint("A", "socket", np.array([0.45, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))}
    good = generate_plan(m, [pts["A"]], CASES[0][2], n_fit=6, n_holdout=0)
    listed = plan_from_joints(m, [{"point": "A", "q": p.q} for p in good.poses], pts)
    assert len(listed) == 6
    with pytest.raises(PlanError, match="outside the joint limits"):
        plan_from_joints(m, [{"point": "A", "q": [10.0] * 6}], pts)
