"""The correction map (docs/map.md): interpolation exactness, sample plans, the seed's 2x2 worked example, the
hexapod with hidden geometric errors, a serial arm, the JSON form and the errors. Ground truth comes from the
simulated world (true geometry) or is computed here independently of the map code."""

import itertools
import json

import numpy as np
import pytest
from station.mocks.world import World

from station.kinematics import load_model, se3
from station.kinematics.parallel import gough_stewart
from station.solver.map import FULL, CorrectionMap, Grid, MapError, build_map, grid_levels, plan, to_vectors

RNG = np.random.default_rng(5)


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


# ---- interpolation ---------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [1, 2, 3, 6])
def test_affine_fields_are_reproduced_inside_and_beyond_the_grid(n):
    g = Grid.of([np.sort(RNG.uniform(-1, 1, 3)) + 0.1 * k for k in range(n)])
    A, b = RNG.normal(size=(4, n)), RNG.normal(size=4)
    nodes = g.nodes()
    values = nodes @ A.T + b
    x = RNG.uniform(-2, 2, (500, n))  # mostly outside the sampled box: extrapolation
    for mesh in ("grid", "simplex"):
        np.testing.assert_allclose(g.interpolate(values, x, mesh), x @ A.T + b, atol=1e-9)


def test_multilinear_reproduces_multilinear_fields_and_barycentric_does_not():
    g = Grid.of([[0.0, 0.4, 1.0], [0.0, 1.0], [-1.0, 0.5, 1.0]])
    f = lambda x: (x[:, 0] * x[:, 1] * x[:, 2] - 2 * x[:, 0] * x[:, 2] + x[:, 1])[:, None]  # noqa: E731
    x = RNG.uniform(-0.5, 1.5, (300, 3))
    np.testing.assert_allclose(g.multilinear(f(g.nodes()), x), f(x), atol=1e-12)
    assert np.abs(g.barycentric(f(g.nodes()), x) - f(x)).max() > 0.05


def test_barycentric_uses_the_kuhn_simplex_vertices():
    """Inside one simplex the barycentric weights reproduce the point from the simplex's vertices."""
    g = Grid.of([[0.0, 1.0]] * 3)
    nodes = g.nodes()
    x = RNG.uniform(0, 1, (200, 3))
    np.testing.assert_allclose(g.barycentric(nodes, x), x, atol=1e-14)  # coordinates are affine
    simp = g.simplices()
    assert simp.shape == (6, 4)  # 3! Kuhn simplices of the unit cube, all sharing its main diagonal
    assert all(s[0] == 0 and s[-1] == 7 for s in simp)


def test_fill_continues_affine_fields_exactly_and_is_smooth():
    g = Grid.of(grid_levels(np.zeros(4), np.ones(4), 3))
    nodes = g.nodes()
    A = RNG.normal(size=(2, 4))
    truth = nodes @ A.T + 0.3
    known = RNG.random(g.size) > 0.4
    filled = g.fill(np.where(known[:, None], truth, 1e3), known)
    np.testing.assert_allclose(filled, truth, atol=1e-9)
    quad = (nodes ** 2).sum(axis=1, keepdims=True)
    known = np.ones(g.size, dtype=bool)
    known[0] = False  # a missing corner of a quadratic bowl: continued along the curvature, close to the truth
    assert abs(g.fill(np.where(known[:, None], quad, 0.0), known)[0, 0] - quad[0, 0]) < 0.2


def test_grid_levels_follow_the_seed():
    lv = grid_levels([0.0, 1.0], [4.0, 2.0], [4, 2])
    np.testing.assert_allclose(lv[0], [0, 1, 2, 3, 4])  # Q + 1 levels, ends included
    np.testing.assert_allclose(lv[1], [1, 1.5, 2])
    lv = grid_levels([0.0], [4.0], 4, exclude_ends=True)
    np.testing.assert_allclose(lv[0], [1, 2, 3])  # W(1..Q-1): the ends a(i), b(i) left out
    with pytest.raises(ValueError):
        grid_levels([0.0], [1.0], 1, exclude_ends=True)


# ---- plans -------------------------------------------------------------------------------------------
def _big_hexapod():
    g = load_model("hexapod").geometry()
    return gough_stewart("wide-hexapod", g["base"], g["platform"], [0.45, 0.6], [0, 0, 0.5, 0, 0, 0])


def test_plan_leaves_out_what_cannot_be_assembled_and_says_why():
    m = _big_hexapod()
    p = plan(m, 1)
    assert len(p.x) + len(p.dropped) == 64 and len(p.dropped) > 0 and len(p.x) > 32
    assert all(p.reasons)
    assert m.fk_solve(p.x).ok.all()
    # a dropped node is either not assemblable or within the safety margin of the boundary
    res = m.fk_solve(p.dropped)
    for ok, why in zip(res.ok, p.reasons, strict=True):
        assert ("workspace boundary" in why) if ok else ("cannot be assembled" in why)
    s = plan(load_model("struts2"), 2, mesh="simplex")
    assert len(s.x) == 9 and len(s.dropped) == 0 and s.mesh == "simplex"
    e = plan(load_model("struts2"), 4, exclude_ends=True)
    np.testing.assert_allclose(np.unique(e.x[:, 0]), [0.35, 0.4, 0.45])


# ---- the seed's worked example (figs. 1-7) -----------------------------------------------------------
def _hinge(pivots, L, branch=1):
    """Where two struts of lengths L meet, from the circle-circle intersection (independent of the model code)."""
    c1, c2 = pivots
    d = np.linalg.norm(c2 - c1)
    e = (c2 - c1) / d
    n = np.array([-e[1], e[0]])
    a = (L[:, 0] ** 2 - L[:, 1] ** 2 + d * d) / (2 * d)
    return c1 + a[:, None] * e + branch * np.sqrt(L[:, 0] ** 2 - a ** 2)[:, None] * n


SEED_ERRORS = {"pivot.1.x": 0.4e-3, "pivot.2.y": -0.6e-3, "strut.1.offset": 0.25e-3, "strut.2.offset": -0.3e-3}


def test_seed_2x2_worked_example():
    nominal = load_model("struts2")
    truth = nominal.with_params({k: nominal.param(k) + v for k, v in SEED_ERRORS.items()})
    L1, L2 = 0.33, 0.47
    p = plan(nominal, 1, lower=[L1, L1], upper=[L2, L2])
    np.testing.assert_allclose(p.x, [[L1, L1], [L1, L2], [L2, L1], [L2, L2]])  # (L1,L1),(L1,L2),(L2,L1),(L2,L2)
    # GDK(x): the true robot, computed here from its true pivots and strut offsets
    tp = np.array([[truth.param("pivot.1.x"), truth.param("pivot.1.y")],
                   [truth.param("pivot.2.x"), truth.param("pivot.2.y")]])
    true_len = p.x + np.array([truth.param("strut.1.offset"), truth.param("strut.2.offset")])
    gdk = _hinge(tp, true_len)
    np.testing.assert_allclose(truth.fk(p.x)[:, :2, 3], gdk, atol=1e-12)
    cm = build_map(nominal, p.x, gdk, ("x", "y"))
    # KSF_PM(x) = x - IK(GDK(x)): IK of the nominal robot = distances to the nominal pivots
    ksf = p.x - np.linalg.norm(gdk[:, None, :] - nominal.geometry()["pivots"][None], axis=2)
    np.testing.assert_allclose(cm.samples_summand, ksf, atol=1e-12)
    np.testing.assert_allclose(cm.summand(p.x), ksf, atol=1e-12)
    # figs. 6-7: every other point of KSF_KR is the bilinear blend of the four corner summands
    s = RNG.uniform(0, 1, (50, 2))
    x = L1 + (L2 - L1) * s
    blend = (ksf[0] * ((1 - s[:, 0]) * (1 - s[:, 1]))[:, None] + ksf[1] * ((1 - s[:, 0]) * s[:, 1])[:, None]
             + ksf[2] * (s[:, 0] * (1 - s[:, 1]))[:, None] + ksf[3] * (s[:, 0] * s[:, 1])[:, None])
    np.testing.assert_allclose(cm.summand(x), blend, atol=1e-15)
    # [0090]-[0091]: the sample poses themselves are reached exactly by the calibrated control
    c, _ = cm.command(nominal, gdk, ("x", "y"))
    np.testing.assert_allclose(c, p.x, atol=1e-12)
    # and inside the square the error shrinks by far (held-out targets)
    targets = truth.fk(L1 + 0.02 + (L2 - L1 - 0.04) * RNG.uniform(0, 1, (200, 2)))[:, :2, 3]
    before = np.linalg.norm(truth.fk(nominal.ik_closed(targets)[0])[:, :2, 3] - targets, axis=1)
    after = np.linalg.norm(truth.fk(cm.command(nominal, targets, ("x", "y"))[0])[:, :2, 3] - targets, axis=1)
    assert rms(after) < 0.02 * rms(before)
    # measuring kinematics: DK(x - KSF(x)) at the samples is the measured pose
    pose, cols = cm.measure(nominal, p.x)
    assert cols == ("x", "y")
    np.testing.assert_allclose(pose, gdk, atol=1e-12)


# ---- exactness on affine configuration errors ----------------------------------------------------------
@pytest.mark.parametrize("mesh", ["grid", "simplex"])
def test_affine_actuator_errors_are_corrected_exactly_everywhere(mesh):
    """A robot whose actuators read an affine function of the true ones: KSF is affine, so the map is exact
    at every target, also beyond the sampled box (plan without the interval ends)."""
    m = load_model("hexapod")
    A = np.eye(6) + 2e-3 * RNG.standard_normal((6, 6))
    b = 3e-4 * RNG.standard_normal(6)
    gdk = lambda x: m.fk(x @ A.T + b)  # noqa: E731  the reached pose when x is commanded
    p = plan(m, 4, exclude_ends=True, mesh=mesh)
    cm = build_map(m, p.x, to_vectors(gdk(p.x), FULL), FULL, mesh=mesh)
    q = m.lower + 0.01 + (m.upper - m.lower - 0.02) * RNG.uniform(0, 1, (100, 6))  # reaches the unsampled ends
    T = m.fk(q)
    c, _ = cm.command(m, to_vectors(T, FULL), FULL)
    np.testing.assert_allclose(gdk(c), T, atol=1e-10)
    pose, _ = cm.measure(m, c)
    np.testing.assert_allclose(se3.pose_to_matrix(pose, "rotvec"), T, atol=1e-10)


# ---- hexapod with hidden geometric errors --------------------------------------------------------------
def _held_out(world, n, rng):
    nom = world.nominal
    q = nom.lower + 0.01 * (nom.upper - nom.lower) + 0.98 * (nom.upper - nom.lower) * rng.uniform(0, 1, (n, 6))
    res = world.truth.fk_solve(q)
    return res.T[res.ok]


@pytest.mark.parametrize("mesh", ["grid", "simplex"])
def test_hexapod_q2_removes_99_percent_of_the_error(mesh):
    w = World.default("hexapod", seed=0)
    nom = w.nominal
    p = plan(nom, 2, mesh=mesh)
    # the robot is driven to every planned configuration and its true pose measured (noise-free)
    measured = w.truth.fk(p.x, guess=nom.fk(p.x))
    cm = build_map(nom, p.x, to_vectors(measured, FULL), FULL, mesh=mesh)
    P = _held_out(w, 300, np.random.default_rng(9))
    before = np.linalg.norm(w.truth.fk(nom.ik_closed(P)[0], guess=P)[:, :3, 3] - P[:, :3, 3], axis=1)
    c, _ = cm.command(nom, to_vectors(P, FULL), FULL)
    after = np.linalg.norm(w.truth.fk(c, guess=P)[:, :3, 3] - P[:, :3, 3], axis=1)
    assert rms(before) > 3e-4
    assert rms(after) < 0.01 * rms(before), (rms(before), rms(after))


# ---- serial arm: compliance and backlash the parametric model cannot hold ----------------------------------
def test_serial_arm_map_corrects_compliance_and_backlash():
    box_lo = np.radians([-20, -10, -10, -30, -70, -30])
    box_hi = np.radians([20, 30, 30, 30, -30, 30])
    w = World.default("arm6", seed=4, errors={"explicit": {}},
                      joints={"compliance": {"j2": 2e-5, "j3": 3e-5}, "backlash": {"j2": 3e-4, "j4": 2e-4},
                              "payload": 15.0})
    nom = w.nominal

    def reach(x):  # the world: approach every configuration from below (unidirectional), read the true pose
        out = []
        for xi in np.atleast_2d(x):
            w.command_q(xi - 0.01)
            w.command_q(xi)
            out.append(w.tip_pose_true())
        return np.array(out)

    p = plan(nom, 1, lower=box_lo, upper=box_hi)
    cm = build_map(nom, p.x, to_vectors(reach(p.x), FULL), FULL)
    # the samples' own poses are reached exactly: IK(GDK(x)) and the fixed point invert each other
    c, _ = cm.command(nom, cm.samples_pose[:5], FULL)
    np.testing.assert_allclose(c, p.x[:5], atol=1e-9)
    qt = box_lo + (box_hi - box_lo) * (0.1 + 0.8 * RNG.uniform(0, 1, (40, 6)))
    targets = nom.fk(qt)
    before = np.linalg.norm(reach(qt)[:, :3, 3] - targets[:, :3, 3], axis=1)
    c, _ = cm.command(nom, to_vectors(targets, FULL), FULL)
    after = np.linalg.norm(reach(c)[:, :3, 3] - targets[:, :3, 3], axis=1)
    assert rms(before) > 5e-4
    assert rms(after) < 0.2 * rms(before), (rms(before), rms(after))


# ---- JSON, model checks, errors -----------------------------------------------------------------------------
def _small_map(mesh="grid"):
    nom = load_model("struts2")
    truth = nom.with_params({k: nom.param(k) + v for k, v in SEED_ERRORS.items()})
    p = plan(nom, 2, mesh=mesh)
    return nom, truth, build_map(nom, p.x, truth.fk(p.x)[:, :2, 3], ("x", "y"), mesh=mesh)


@pytest.mark.parametrize("mesh", ["grid", "simplex"])
def test_json_round_trip_serves_the_same_map(mesh):
    nom, _, cm = _small_map(mesh)
    back = CorrectionMap.from_dict(json.loads(cm.dumps()))
    x = RNG.uniform(0.29, 0.51, (100, 2))
    np.testing.assert_allclose(back.summand(x), cm.summand(x), atol=0)
    assert back.mesh == mesh and back.statistics["n_samples"] == 9
    doc = cm.to_dict()
    assert doc["format"] == "station-map/1" and doc["mesh"]["type"] == mesh and len(doc["nodes"]["summand"]) == 9
    del doc["nodes"]
    with pytest.raises(MapError, match="missing field 'nodes'"):
        CorrectionMap.from_dict(doc, "m.json")


def test_map_refuses_what_it_cannot_serve():
    nom, truth, cm = _small_map()
    with pytest.raises(MapError, match="outside the map") as e:
        cm.summand([[0.4, 3.0]])
    assert e.value.row == 0 and "\n" not in str(e.value)
    with pytest.raises(MapError, match="unreachable"):
        cm.command(nom, [[0.2, 0.3], [5.0, 5.0]], ("x", "y"))
    with pytest.raises(MapError, match="other side of the pivot line"):
        cm.command(nom, [[0.2, -0.3]], ("x", "y"))
    with pytest.raises(MapError, match="differs from the one the map was built with: pivot.1.x"):
        cm.command(nom.with_params({"pivot.1.x": 0.001}), [[0.2, 0.3]], ("x", "y"))
    with pytest.raises(MapError, match="built for model 'struts2'"):
        cm.command(load_model("hexapod"), [[0.2, 0.3]], ("x", "y"))
    with pytest.raises(MapError, match="needs pose columns x,y"):
        cm.command(nom, [[0.2, 0.3, 0.0]], ("x", "y", "z"))
    p = plan(nom, 2)
    off = p.x.copy()
    off[3, 0] += 0.02  # 20 % of the level spacing off its node
    with pytest.raises(MapError, match="sample 4: configuration is not on the grid"):
        build_map(nom, off, truth.fk(p.x)[:, :2, 3], ("x", "y"), levels=p.levels)  # the plan's grid known
    p = plan(nom, 4)
    off = p.x.copy()
    off[7, 1] += 0.01
    with pytest.raises(MapError, match="sample 8: configuration is not on the grid"):
        build_map(nom, off, truth.fk(p.x)[:, :2, 3], ("x", "y"))  # the grid inferred from the samples
    with pytest.raises(MapError, match="sample 1: correction of x1"):
        build_map(nom, p.x, truth.fk(p.x)[:, :2, 3] * 1e3, ("x", "y"))  # millimetres read as metres


def test_repeated_samples_on_a_node_are_averaged_and_readback_scatter_is_accepted():
    nom, truth, _ = _small_map()
    p = plan(nom, 1)
    x = np.vstack([p.x, p.x + 2e-6])  # encoder readings a few um off the commanded levels
    gdk = truth.fk(x)[:, :2, 3]
    cm = build_map(nom, x, gdk, ("x", "y"))
    assert cm.statistics["n_samples"] == 8 and cm.statistics["n_measured_nodes"] == 4
    per = x - nom.ik_closed(gdk, check_limits=False)[0]
    np.testing.assert_allclose(cm.values, (per[:4] + per[4:]) / 2, atol=1e-15)


def test_map_on_top_of_an_exact_calibration_has_nothing_left_to_correct():
    nom = load_model("struts2")
    truth_values = {k: nom.param(k) + v for k, v in SEED_ERRORS.items()}
    truth = nom.with_params(truth_values)
    p = plan(nom, 2)
    gdk = truth.fk(p.x)[:, :2, 3]
    plain = build_map(nom, p.x, gdk, ("x", "y"))
    on_top = build_map(nom, p.x, gdk, ("x", "y"), calibration=truth_values, calibration_source="exact")
    assert max(plain.statistics["summand_max"]) > 1e-4
    assert max(on_top.statistics["summand_max"]) < 1e-12
    c, _ = on_top.command(nom, gdk, ("x", "y"))  # commands come from the calibrated model
    np.testing.assert_allclose(c, p.x, atol=1e-12)
    assert CorrectionMap.from_dict(json.loads(on_top.dumps())).calibration["parameters"] == pytest.approx(truth_values)


def test_grid_corner_order_is_c_order():
    g = Grid.of([[0, 1], [0, 1, 2]])
    assert [tuple(v) for v in g.nodes()] == list(itertools.product([0, 1], [0, 1, 2]))


# ---- the instrument's measurement model (bench and, later, the tracker emulator) ----------------------------
def test_tracker_noise_has_the_stated_sigma_in_its_own_frame():
    from station.mocks.world.tracker import measure_points, measure_poses, sigma

    tracker = se3.pose_to_matrix(np.array([2.0, 1.0, 0.5, 0.0, 0.0, 0.7]), "rotvec")
    p = np.array([0.3, -0.2, 0.8])
    rng = np.random.default_rng(2)
    local = np.linalg.inv(tracker) @ np.r_[p, 1.0]
    readings = measure_points(np.broadcast_to(p, (4000, 3)), tracker, rng)
    d = float(np.linalg.norm(local[:3]))
    np.testing.assert_allclose(readings.mean(axis=0), local[:3], atol=4 * sigma(d) / np.sqrt(4000))
    np.testing.assert_allclose(readings.std(axis=0), sigma(d), rtol=0.06)  # 15 um + 6 um/m, per axis
    assert sigma(d) == pytest.approx(15e-6 + 6e-6 * d)
    refl = np.array([[0.1, 0, 0], [-0.05, 0.0866, 0], [-0.05, -0.0866, 0.0]])
    T = se3.pose_to_matrix(np.array([0.2, 0.1, 0.6, 0.1, -0.2, 0.3]), "rotvec")
    poses = tracker @ measure_poses(np.broadcast_to(T, (300, 4, 4)), refl, tracker, rng)
    err = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1)
    assert 0.5 * sigma(d) < rms(err) < 2.5 * sigma(d)  # centroid of 3 readings: ~sigma


@pytest.mark.parametrize("centre, span, bad", [([0.0, 0.17, 0.17, 0.0, -0.87, 0.0], 10, False),
                                               ([0.3, -0.9, 1.2, -0.8, 1.2, 0.4], 20, True)])
def test_predicted_residual_foretells_a_serial_map_near_a_singularity(centre, span, bad):
    """arm6: the plan's prediction (no measurement) against what a map built from the world's EXACT true poses
    actually leaves on held-out configurations: near the shoulder singularity both say the map fails."""
    from station.solver.map.plan import predicted_residual

    w = World.default("arm6", seed=7)
    nom = w.nominal
    c = np.array(centre)
    p = plan(nom, 1, mesh="simplex", lower=c - np.radians(span), upper=c + np.radians(span))
    predicted = predicted_residual(nom, p)
    cm = build_map(nom, p.x, to_vectors(w.truth.fk(p.x), FULL), FULL, mesh="simplex")
    lo, hi = p.grid.lower, p.grid.upper
    x = np.random.default_rng(3).uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (200, 6))
    truth = w.truth.fk(x)[:, :3, 3]
    e_nom = np.linalg.norm(nom.fk(x)[:, :3, 3] - truth, axis=1)
    e_map = np.linalg.norm(cm.measure(nom, x)[0][:, :3] - truth, axis=1)
    ratio = np.sqrt(np.mean(e_map ** 2) / np.mean(e_nom ** 2))
    if bad:
        assert predicted > 0.5 and ratio > 0.5, (predicted, ratio)  # refused by correction_map; rightly so
    else:
        assert predicted < 0.2 and ratio < 0.1, (predicted, ratio)
    assert ratio < predicted  # real errors partly look like joint offsets, which the map holds exactly
