"""Collision-aware pose plans: the UR5e demo plan (before it, 14 of 28 poses put the elbow up to 260 mm below the
mounting plane) must keep every link capsule above the plane with its clearance.

Ground truth for "below the plane" is computed here, independently of station.kinematics.collision: the elbow
is the origin of the frame before the elbow joint's rotation (on the elbow axis), read from the kinematic
chain's own frames; link capsules are checked against the plane from the DH frame origins by hand."""

import json
from pathlib import Path

import numpy as np
import pytest

from station.engine.cell import RefPoint, load_cell
from station.engine.plan import PlanError, generate_plan, plan_from_joints, route_from
from station.kinematics import load_model
from station.kinematics.chain import forward
from station.kinematics.collision import Box, Checker, KeepOut

UR_START = [0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The station side of `station demo` (UR5e): the cell file it writes and the model with the cell's tool."""
    from station.cli.run_cmd import write_demo_files

    _, cell_path, _ = write_demo_files("ur", tmp_path_factory.mktemp("demo"), 5, "instant")
    cell = load_cell(cell_path)
    m = load_model("ur5e")
    if cell.tool:
        m = m.with_params({f"tcp.{k}": v for k, v in cell.tool.items()})
    return m, cell


def _joint_points(model, q):
    """(N, n, 3): a point on each joint axis (the frame before the joint's rotation), straight from the chain."""
    _, prefix = forward(model.chain, np.atleast_2d(q), model.params, keep_prefix=True)
    ks = [int(np.flatnonzero(model.chain.joint == i)[0]) for i in range(model.n_joints)]
    return prefix[:, ks][:, :, :3, 3]


def _demo_plan(m, cell, **kw):
    # what zero_offsets asks for in the demo (procedures/zero_offsets.py DEFAULTS, seed 0)
    return generate_plan(m, cell.of_kind("socket"), UR_START, identify="offsets", n_holdout=4, cone_deg=50.0,
                         seed=0, **kw)


def test_the_checker_finds_every_elbow_below_the_base_in_the_plan_before_keepouts(demo):
    """The demo plan of the planner before this change (recorded: tests/data), as the issue saw it."""
    m, _ = demo
    rec = json.loads((Path(__file__).parents[1] / "data" / "ur5e_demo_plan_before_keepout.json").read_text())
    q = np.array(rec["q"])
    elbow_z = _joint_points(m, q)[:, 2, 2]  # joint 3 (elbow) axis point, height above the base plane
    below = elbow_z < 0
    assert len(q) == 28 and below.sum() == 14 and -0.27 < elbow_z.min() < -0.25
    hits = Checker(m, None).hits(q)
    flagged = np.array([h is not None for h in hits])
    assert flagged[below].all()
    for h in (h for h, b in zip(hits, below, strict=True) if b):
        assert h.obstacle == "mounting plane" and h.link == 2 and h.distance < -0.2
        assert "link 2 (shoulder-elbow)" in h.describe() and "'mounting plane'" in h.describe()
    # the approach poses as well: they differ from the touch poses by 30 mm at the tool
    assert sum(h is not None for h in Checker(m, None).hits(np.array(rec["approach_q"]))) >= 14


def test_demo_plan_keeps_every_link_above_the_mounting_plane(demo):
    m, cell = demo
    plan = _demo_plan(m, cell)
    radii = np.array(m.source["collision"]["link_radii"])
    for which in ("q", "approach_q"):
        q = np.array([getattr(p, which) for p in plan.poses])
        P = _joint_points(m, q)  # shoulder, elbow, wrist points: capsule ends of the links that can go down
        z = P[:, 1:, 2] - np.maximum(radii[1:], radii[:-1])[None, :]
        assert z.min() >= 0.01 - 1e-9, f"{which}: a joint housing reaches {z.min() * 1e3:.0f} mm"
        assert all(h is None for h in Checker(m, None).hits(q))


# ---- keep-out boxes and paths, checked by an independent brute force ------------------------------------------
def _point_box_distance(P, box):
    local = (P - box.center) @ box.rotation
    clamped = np.clip(local, -box.half, box.half)
    inside = np.all(np.abs(local) <= box.half, axis=-1)
    return np.where(inside, -np.min(box.half - np.abs(local), axis=-1), np.linalg.norm(local - clamped, axis=-1))


def _worst_clearance(model, q, box, n=24):
    """(N,) smallest distance of the arm's surface to ``box`` minus nothing (m), from the chain's frames: link
    capsules between the joint axis points, the flange (last link ends at its face) and the tool up to 20 mm
    before the TCP, each sampled at ``n`` points."""
    q = np.atleast_2d(q)
    T, prefix = forward(model.chain, q, model.params, keep_prefix=True)
    ks = [int(np.flatnonzero(model.chain.joint == i)[0]) for i in range(model.n_joints)]
    tcp0 = model.index("tcp.x")
    flange = prefix[:, tcp0, :3, 3]
    pts = np.concatenate([prefix[:, ks][:, :, :3, 3], flange[:, None], T[:, None, :3, 3]], axis=1)
    radii = list(model.source["collision"]["link_radii"]) + [0.01]
    out = np.full(len(q), np.inf)
    for i, r in enumerate(radii):
        a, b = pts[:, i], pts[:, i + 1]
        d = b - a
        L = np.linalg.norm(d, axis=1, keepdims=True)
        trim = r if i == len(radii) - 2 else (0.03 if i == len(radii) - 1 else 0.0)
        b = b - d / np.maximum(L, 1e-12) * np.minimum(trim, L)
        s = np.linspace(0, 1, n)[None, :, None]
        dist = _point_box_distance(a[:, None] + s * (b - a)[:, None], box).min(axis=1) - r
        out = np.minimum(out, np.where(L[:, 0] > 1e-3, dist, np.inf))
    return out


def _motions(plan, start):
    """Every straight joint move the procedure makes: start -> vias -> approach -> touch -> approach -> ..."""
    moves, cur = [], np.asarray(start, float)
    for p in plan.poses:
        for nxt in [*map(np.asarray, p.via), p.approach_arr, p.q_arr, p.approach_arr]:
            moves.append((cur, nxt))
            cur = nxt
    return moves


def _dense(a, b, step=0.002, reach=1.4):
    n = max(2, int(np.ceil(np.abs(b - a).sum() * reach / step)) + 1)
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


FENCE = Box.from_corners("fence", [0.15, 0.10, 0.0], [0.75, 0.40, 0.6])


def test_a_fixture_box_in_the_cell_is_kept_clear_on_every_pose_and_path():
    m = load_model("ur5e").with_params({"tcp.z": 0.10})  # a 100 mm stylus
    pt = RefPoint("A", "socket", np.array([0.45, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))
    start = np.array(UR_START)
    ko = KeepOut(KeepOut.default().mounting, (FENCE,))
    unaware = generate_plan(m, [pt], start)  # knows the table, not the fence 100 mm beside the socket
    hit_before = _worst_clearance(m, np.array([p.q for p in unaware.poses]), FENCE) < 0
    assert hit_before.sum() >= 5
    plan = generate_plan(m, [pt], start, keep_out=ko)
    q = np.array([p.q for p in plan.poses])
    assert np.abs(m.position(q) - pt.position).max() < 1e-6 and len(plan.of_set("fit")) == 20
    assert _worst_clearance(m, q, FENCE).min() >= 0.01 - 1e-4
    for a, b in _motions(plan, start):
        Q = _dense(a, b)
        assert _worst_clearance(m, Q, FENCE).min() >= 0.01 - 0.0025  # the path keeps the clearance (5 mm step)
        assert (_joint_points(m, Q)[:, 1:, 2] - 0.06).min() >= 0.0  # and every joint housing above the table
    assert plan.settings["keep_out"]["keep_out"][0]["name"] == "fence"


def test_a_point_inside_a_keep_out_is_refused_naming_the_obstacle():
    m = load_model("ur5e").with_params({"tcp.z": 0.10})
    pt = RefPoint("A", "socket", np.array([0.45, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))
    cage = Box.from_corners("cage", [0.35, -0.1, 0.0], [0.55, 0.1, 0.2])
    with pytest.raises(PlanError) as e:
        generate_plan(m, [pt], UR_START, keep_out=KeepOut(KeepOut.default().mounting, (cage,)))
    msg = str(e.value)
    assert "reference point A" in msg and "clear of the keep-outs" in msg and "enters 'cage'" in msg
    assert "\n" not in msg


def _down_at(m, p, seed_q):
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # tool z pointing down
    T[:3, 3] = p
    r = m.ik(T, seed_q, max_iter=300)
    assert r.ok[0]
    return r.q[0]


def test_a_move_from_a_jogged_position_gets_a_via_over_a_wall():
    """A resumed session: the arm stands above socket A (jogged there), the next approach pose is above B on
    the other side of a low wall; the straight joint path swings the stylus through the wall."""
    m = load_model("ur5e").with_params({"tcp.z": 0.10})
    wall = Box.from_corners("wall", [0.25, -0.04, 0.0], [0.70, 0.04, 0.15])
    ko = KeepOut(KeepOut.default().mounting, (wall,))
    here = _down_at(m, [0.45, 0.20, 0.08], np.array(UR_START) + [np.pi, 0, 0, 0, 0, 0])  # facing the cell
    there = _down_at(m, [0.45, -0.20, 0.08], here)
    assert Checker(m, ko).path_hit(here, there).obstacle == "wall"
    path = route_from(m, ko, here, [there], what="pose 3")
    assert len(path) >= 2 and np.allclose(path[-1], there)
    cur = here
    for nxt in path:
        Q = _dense(cur, nxt)
        assert _worst_clearance(m, Q, wall).min() >= 0.01 - 0.0025 - 0.002  # run-time slack 2 mm
        assert (_joint_points(m, Q)[:, 1:, 2] - 0.06).min() >= 0.0
        cur = nxt
    # the shoulder cannot swing the upper arm from forward to backward under the shoulder: refused in one line
    fwd = np.array([0.0, -0.3, 0.0, -1.5708, 0.0, 0.0])
    back = np.array([0.0, np.pi + 0.3, 0.0, -1.5708, 0.0, 0.0])
    with pytest.raises(PlanError, match=r"^pose 0: link \d \(.*\) would be \d+ mm inside obstacle 'mounting plane' "
                                        r".*no via pose avoids it"):
        route_from(m, KeepOut.default(), fwd, [back], what="pose 0")
    with pytest.raises(PlanError, match=r"pose 0: target .*: link \d \(.*\) would be \d+ mm inside obstacle"):
        route_from(m, ko, here, [np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0])], what="pose 0")


def test_a_listed_pose_below_the_table_is_refused():
    m = load_model("ur5e")
    pts = {"A": RefPoint("A", "socket", np.array([0.45, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))}
    rec = json.loads((Path(__file__).parents[1] / "data" / "ur5e_demo_plan_before_keepout.json").read_text())
    below = next(q for q in rec["q"] if _joint_points(m, np.array(q))[0, 2, 2] < 0)
    with pytest.raises(PlanError, match=r"listed pose 0: link 2 \(shoulder-elbow\) would be \d+ mm inside "
                                        r"obstacle 'mounting plane'"):
        plan_from_joints(m, [{"point": "A", "q": below}], pts)


def test_moves_between_poses_keep_the_tip_out_of_the_references_themselves():
    """A reference is a body (a socket's nest, a needle's post) under its point: only the approach to it may
    bring the tip there; a move between poses that dips the tip into it is refused, the links may pass by."""
    from station.engine.plan import reference_body, transit_checker

    m = load_model("ur5e").with_params({"tcp.z": 0.1})
    q = np.array([0.0, -1.2, 1.9, -2.27, -1.5708, 0.0])  # tool pointing down
    tip = m.fk(q)[:3, 3]
    pt = RefPoint("A", "socket", tip + np.array([0.0, 0.0, 0.006]), np.array([0.0, 0.0, 1.0]), radius=0.008)
    body = reference_body(pt)  # independent check of its extent: a box under the point, as wide as its radius
    assert np.allclose(body.center, pt.position - [0, 0, 0.015]) and np.allclose(body.half, [0.008, 0.008, 0.015])
    above = q.copy()
    above[1] -= 0.25  # the tool lifted well clear
    plain = Checker(m, KeepOut.none())
    transit = transit_checker(m, KeepOut.none(), points=[pt])
    assert plain.path_hit(above, q) is None  # the links and the trimmed tool see nothing there
    h = transit.path_hit(above, q)
    assert h is not None and h.obstacle == "reference A" and h.link_name == "tool tip"
    # from the touch itself the way out is checked as the way in was
    assert transit.leaving(q).path_hit(q, above) is None
    # a link passing through the reference's box is not this check's business (masked: tip only)
    assert not transit.mask[:-1, -1].any() and transit.mask[-1, -1]
