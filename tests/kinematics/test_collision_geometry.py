"""Link capsules and keep-out distances (station.kinematics.collision) against brute force: dense samples of the
capsule axis, point-to-box distances by clamping, the envelope against the DH frames, path scans against dense
sampling; the jog-target check names the link and the obstacle."""

import re

import numpy as np
import pytest

from station.engine.cell import check_clear, check_path_clear
from station.kinematics import builtin_names, load_model
from station.kinematics.chain import forward
from station.kinematics.collision import (
    Box,
    Checker,
    KeepOut,
    Plane,
    _box_distance,
    _plane_distance,
    capsules,
    envelope,
    radii_of,
)
from station.kinematics.se3 import rpy_to_matrix
from station.robot.errors import LimitError

RNG = np.random.default_rng(7)


def _point_box_distance(P, box):
    """Independent: outside, the distance to the clamped point; inside, minus the distance to the nearest face."""
    local = (P - box.center) @ box.rotation
    clamped = np.clip(local, -box.half, box.half)
    out = np.linalg.norm(local - clamped, axis=-1)
    inside = np.all(np.abs(local) <= box.half, axis=-1)
    depth = np.min(box.half - np.abs(local), axis=-1)
    return np.where(inside, -depth, out)


def test_segment_to_plane_and_box_match_dense_sampling():
    A = RNG.uniform(-0.5, 0.5, (150, 3))
    B = RNG.uniform(-0.5, 0.5, (150, 3))
    t = np.linspace(0, 1, 8001)[None, :, None]
    S = A[:, None] + t * (B - A)[:, None]  # (150, 8001, 3)
    plane = Plane.through("p", [0.1, -0.2, 0.05], [0.3, -0.5, 1.0])
    np.testing.assert_allclose(_plane_distance(A, B, plane), (S @ plane.normal).min(axis=1) - plane.offset,
                               atol=1e-12)
    for _ in range(5):
        box = Box("b", RNG.uniform(-0.2, 0.2, 3), RNG.uniform(0.02, 0.3, 3), rpy_to_matrix(RNG.uniform(-3, 3, 3)))
        brute = _point_box_distance(S, box).min(axis=1)
        got = _box_distance(A, B, box)
        # 8001 samples resolve the minimum to half a spacing (< 0.11 mm); the search must never be larger
        assert np.all(got <= brute + 1e-9)
        np.testing.assert_allclose(got, brute, atol=1.1e-4)
        assert (got < 0).any() and (got > 0).any()  # both penetrating and clear segments were tried


def test_ur5e_envelope_follows_the_dh_frames():
    m = load_model("ur5e")
    env = envelope(m)
    q = RNG.uniform(-np.pi, np.pi, (5, 6))
    A, B, r = capsules(m, q, env)
    _, prefix = forward(m.chain, q, m.params, keep_prefix=True)
    ks = [int(np.flatnonzero(m.chain.joint == i)[0]) for i in range(6)]
    axis_pts = prefix[:, ks][:, :, :3, 3]  # a point on each joint axis (DH frame i-1 origin)
    flange = m.fk(q)[:, :3, 3]  # no tool: TCP = flange
    np.testing.assert_allclose(A[:, :5], axis_pts[:, :5], atol=1e-12)  # base, shoulder, elbow, wrist1, wrist2
    np.testing.assert_allclose(B[:, :5], axis_pts[:, 1:6], atol=1e-12)
    # the last link ends at the flange face: its cap reaches the flange, not a radius beyond
    end = B[:, 5] + r[5] * (B[:, 5] - A[:, 5]) / np.linalg.norm(B[:, 5] - A[:, 5], axis=1)[:, None]
    np.testing.assert_allclose(end, flange, atol=1e-12)
    np.testing.assert_allclose(r * 1e3, [75, 60, 50, 45, 45, 45])
    assert env.names[1] == "shoulder-elbow" and env.names[5] == "wrist3-flange"


@pytest.mark.parametrize("name", [n for n in builtin_names() if load_model(n).convention != "parallel"])
def test_the_base_link_is_not_checked_against_the_plane_it_stands_on(name):
    m = load_model(name)
    ch = Checker(m, None)
    checked = {int(k) for k in ch.env.link[ch.mask[:, 0]]}
    assert 1 not in checked  # the base column stands on the table by design
    # fr3 (Craig frames): link 2 carries no translation (the upper arm is joint 3's d), 8 is the tool
    expect = {"scara": {3, 5}, "omx": {2, 3, 4}, "arm6": {2, 3, 4, 6},
              "fr3": {3, 4, 5, 6, 8}}.get(name, {2, 3, 4, 5, 6})
    assert checked == expect
    # every built-in arm's default start pose is clear (the planner refuses to start from a violation)
    from station.mocks.world.cell import DEFAULTS

    assert ch.hits(np.array(DEFAULTS[name]["start"])[None])[0] is None


def test_a_tool_is_checked_except_its_tip():
    m = load_model("ur5e").with_params({"tcp.z": 0.15})
    q = np.array([0.0, -1.2, 1.9, -2.27, -1.5708, 0.0])  # tool pointing down
    tip = m.fk(q)[:3, 3]
    ch = Checker(m, KeepOut(Plane("table", np.array([0, 0, 1.0]), tip[2] - 0.015, 0.0)))
    assert ch.hits(q[None])[0] is None  # the last 20 mm of the tool may touch (tip 15 mm below the surface)
    ch = Checker(m, KeepOut(Plane("table", np.array([0, 0, 1.0]), tip[2] + 0.05, 0.0)))
    h = ch.hits(q[None])[0]
    assert h is not None and h.link == 7 and h.link_name == "tool" and "tool would be" in h.describe()


def test_a_move_between_poses_keeps_the_tip_out_and_may_leave_a_touch():
    m = load_model("ur5e").with_params({"tcp.z": 0.15})
    q = np.array([0.0, -1.2, 1.9, -2.27, -1.5708, 0.0])  # tool pointing down
    tip = m.fk(q)[:3, 3]
    table = KeepOut(Plane("table", np.array([0, 0, 1.0]), tip[2] + 0.005, 0.01))  # the tip 5 mm below its top
    plain, transit = Checker(m, table), Checker(m, table, tip=True)
    assert plain.hits(q[None])[0] is None  # the approach to a reference may bring the tip there
    h = transit.hits(q[None])[0]
    assert h is not None and h.link_name == "tool tip" and h.clearance == 0.0 and "tool tip would be" in h.describe()
    # the tip's own depth (independent: the TCP's height against the plane, less the tool's radius)
    assert h.distance == pytest.approx(tip[2] - (tip[2] + 0.005) - radii_of(m)[1], abs=1e-9)
    above = q.copy()
    above[1] -= 0.25  # the shoulder lifts the tool off the table
    assert transit.hits(above[None])[0] is None
    # a move between poses that ends with the tip in the table is refused; the plain check lets it through
    assert plain.path_hit(above, q) is None and transit.path_hit(above, q) is not None
    # the way out of a touch is checked as the way in was; from a clear pose the tip check holds
    assert transit.leaving(q) is not transit and transit.leaving(q).path_hit(q, above) is None
    assert transit.leaving(above) is transit


def test_path_scan_agrees_with_dense_sampling():
    m = load_model("ur5e")
    ch = Checker(m, KeepOut(Plane("mounting plane", np.array([0, 0, 1.0]), 0.0, 0.01),
                            (Box.from_corners("fixture", [0.2, -0.3, 0.0], [0.5, 0.1, 0.25]),)))
    start = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
    QA = np.clip(start + RNG.normal(0, 0.8, (20, 6)), -6, 6)
    QB = np.clip(start + RNG.normal(0, 0.8, (20, 6)), -6, 6)
    fast = ch.scan(QA, QB, step=0.005)
    for qa, qb, h in zip(QA, QB, fast, strict=True):
        n = max(2, int(np.ceil(ch.travel(qa, qb)[0] / 0.001)) + 1)  # samples of the truth, 1 mm apart
        M = ch.margins(qa + np.linspace(0, 1, n)[:, None] * (qb - qa)).min(axis=(1, 2))
        if h is None:
            assert M.min() >= -0.0025 - 1e-9  # clear at 5 mm resolution: nothing deeper than half a step
        if M.min() < -0.005:
            assert h is not None
    assert sum(h is not None for h in fast) >= 5 and sum(h is None for h in fast) >= 5


def test_a_path_blocked_in_the_middle_is_found_though_both_ends_are_clear():
    m = load_model("ur5e")
    ch = Checker(m, None)
    a = np.array([0.0, -0.3, 0.0, -1.5708, 0.0, 0.0])  # arm forward, 17 deg above horizontal
    b = a.copy()
    b[1] = -np.pi + 0.3  # the same backwards: the straight joint path swings the shoulder down through the table
    b[1] += 2 * np.pi
    assert ch.hits(np.array([a, b]))[0] is None and ch.hits(np.array([a, b]))[1] is None
    h = ch.path_hit(a, b)
    assert h is not None and h.obstacle == "mounting plane" and h.link >= 2
    with pytest.raises(LimitError, match=r"link \d \(.*\) would be .* inside obstacle 'mounting plane'"):
        check_path_clear(m, None, a, b, "jog")
    check_path_clear(m, None, a, np.array([0.0, -0.6, 0.0, -1.5708, 0.0, 0.0]))  # up, not through the table


def test_check_clear_names_link_and_obstacle_in_one_line():
    m = load_model("ur5e")
    down = np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0])  # shoulder 34 deg below horizontal
    with pytest.raises(LimitError) as e:
        check_clear(m, None, down, "jog")
    msg = str(e.value)
    assert re.fullmatch(r"jog: link \d \([a-z0-9]+-[a-z0-9]+\) would be \d+ mm inside obstacle 'mounting plane' "
                        r"\(clearance 10 mm\); refused", msg), msg
    check_clear(m, None, np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]))  # the home pose is clear
    box = KeepOut(None, (Box.from_corners("camera", [-0.9, -0.3, 0.0], [-0.6, 0.3, 0.4]),))
    with pytest.raises(LimitError, match="obstacle 'camera'"):
        check_clear(m, box, np.zeros(6))  # the stretched arm lies across the camera box
    check_clear(m, KeepOut.none(), down)  # no keep-out at all: nothing to refuse


def _models_with_urdf(tmp_path):
    import urdf_robots

    names = [n for n in builtin_names() if load_model(n).convention != "parallel"]
    return [load_model(n) for n in names] + [load_model(str(urdf_robots.write(tmp_path, "arm7")), tip_link="ball")]


def test_key_points_are_the_chain_frames_for_every_model(tmp_path):
    """The collision key points (folded chain, ``_origins``) are the origins of the frames after each element the
    envelope asks for, as the plain chain FK gives them — for every built-in model and a URDF arm whose envelope
    asks for one element in two slots (two capsules sharing an end; those slots were left unwritten once)."""
    from station.kinematics.collision import _origins

    for m in _models_with_urdf(tmp_path):
        env = envelope(m)
        q = RNG.uniform(-1.0, 1.0, (4, m.n_joints))
        T, prefix = forward(m.chain, q, m.params, keep_prefix=True)
        after = np.concatenate([prefix[:, 1:], T[:, None]], axis=1)[..., :3, 3]  # frame after element k
        want = np.stack([np.zeros((len(q), 3)) if e < 0 else after[:, e] for e in env.element], axis=1)
        got = _origins(m, q, env.element)
        np.testing.assert_allclose(got, want, atol=1e-12, err_msg=m.name)
