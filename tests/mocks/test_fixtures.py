"""Per-touch weights and several fixture positions in one solve.

Ground truth: the simulated world (``station.mocks.world``): its true robot makes the touches, its sockets are
the first fixture position; the second position is the same fixture moved rigidly (the known distance between
its sockets does not change)."""

import json

import numpy as np
import pytest
from clirunner import station_proc
from station.mocks.world import World

from station.kinematics import se3
from station.solver import Observations, SolverInputError, solve
from station.solver.simulate import touch_observations

HIDDEN = {"dh.j2.a": 8e-4, "dh.j3.a": -6e-4, "offset.j2": 1e-3, "offset.j3": -7e-4, "tcp.z": 3e-4}
NOISE = 20e-6
LENGTHS = ("dh.j2.a", "dh.j3.a")
MOVE = se3.pose_to_matrix([0.05, 0.12, 0.03, 0.0, 0.0, 0.35], "rpy")  # the fixture moved between sessions


@pytest.fixture(scope="module")
def world():
    return World.default("ur5e", seed=5, errors={"explicit": HIDDEN, "random": {}})


@pytest.fixture(scope="module")
def rigid_world():
    """Hidden zero offsets and TCP only: what ``offsets,tcp`` models completely."""
    return World.default("ur5e", seed=6, errors={"explicit": {k: v for k, v in HIDDEN.items() if k not in LENGTHS},
                                                 "random": {}})


def positions(world) -> dict[str, dict[str, np.ndarray]]:
    a, b = world.points["A"].position, world.points["B"].position
    moved = {lb: MOVE[:3, :3] @ p + MOVE[:3, 3] for lb, p in (("A", a), ("B", b))}
    return {"1": {"A": a, "B": b}, "2": moved}


def fixture_data(world, rng, n=15, noise=NOISE) -> Observations:
    q, pt, fx = [], [], []
    for f, pts in positions(world).items():
        o = touch_observations(world.truth, pts, n, rng, noise=noise, spread=0.5)
        q.append(o.q)
        pt += list(o.point)
        fx += [f] * len(o)
    return Observations(np.vstack(q), np.array(pt, dtype=object), fixture=np.array(fx, dtype=object))


def test_two_fixture_positions_fit_jointly(world):
    obs = fixture_data(world, np.random.default_rng(1))
    d = float(np.linalg.norm(world.points["A"].position - world.points["B"].position))
    res = solve(world.nominal, obs, "offsets,dh,tcp", "unknown", distances=[("A", "B", d)])
    assert res.trusted, res.failure
    # each position has its own points, and each is where the world put it
    pts = res.points()
    assert set(pts) == {"A@1", "B@1", "A@2", "B@2"}
    for f, ps in positions(world).items():
        for lb, p in ps.items():
            assert np.linalg.norm(pts[f"{lb}@{f}"] - p) < 1e-3, (lb, f)
    # the known distance holds at both positions
    cons = {c["fixture"]: c for c in res.constraints}
    assert set(cons) == {"1", "2"}
    for c in cons.values():
        assert c["labels"] == ["A", "B"] and abs(c["residual_m"]) < 4 * c["stated_std_m"]
    for n in LENGTHS + ("offset.j2", "offset.j3"):
        p = res.parameters[n]
        assert abs(p.value - world.truth.param(n)) < 4 * p.std, (n, p.value, p.std)
    # one position alone knows less: the joint fit's std is smaller
    one = obs.subset(obs.fixture == "1")
    res1 = solve(world.nominal, Observations(one.q, one.point), "offsets,dh,tcp", "unknown", distances=[("A", "B", d)])
    for n in LENGTHS:
        assert res.parameters[n].std < res1.parameters[n].std


def test_without_a_fixture_column_moved_points_do_not_fit(world):
    """The same touches with the positions merged under one label: the model cannot fit them (what the
    fixture column is for)."""
    obs = fixture_data(world, np.random.default_rng(2), 8)
    merged = solve(world.nominal, Observations(obs.q, obs.point), "offsets,tcp", "unknown")
    assert merged.sigma_m > 100 * NOISE or not merged.trusted


def test_weight_is_an_inverse_variance_scale(rigid_world):
    """A touch of weight w counts like w copies of it (declared noise: the estimate is exactly that of the
    duplicated data), and noisy touches weighted 1/16 leave the fitted sigma at the good touches' noise."""
    world = rigid_world
    rng = np.random.default_rng(3)
    obs = touch_observations(world.truth, {lb: world.points[lb].position for lb in "AB"}, 12, rng, noise=NOISE,
                             spread=0.5)
    w = np.ones(len(obs))
    w[::3] = 2.0
    dup = np.concatenate([np.arange(len(obs)), np.flatnonzero(w == 2.0)])
    a = solve(world.nominal, Observations(obs.q, obs.point, weight=w), "offsets,tcp", "unknown", noise=NOISE)
    b = solve(world.nominal, Observations(obs.q[dup], obs.point[dup]), "offsets,tcp", "unknown", noise=NOISE)
    for n in ("offset.j2", "offset.j3", "tcp.z"):
        # equal to the fit's convergence tolerance (a step below 1e-4 std stops it)
        assert a.parameters[n].value == pytest.approx(b.parameters[n].value, abs=1e-2 * b.parameters[n].std)
        assert a.parameters[n].std == pytest.approx(b.parameters[n].std, rel=1e-3)
    # half the touches 4x noisier, weighted 1/16: sigma is the good touches' noise, and the estimate is
    # better than the unweighted one's claim
    good = touch_observations(world.truth, {lb: world.points[lb].position for lb in "AB"}, 15, rng, noise=NOISE,
                              spread=0.5)
    bad = touch_observations(world.truth, {lb: world.points[lb].position for lb in "AB"}, 15, rng,
                             noise=4 * NOISE, spread=0.5)
    q = np.vstack([good.q, bad.q])
    pt = np.concatenate([good.point, bad.point])
    wts = np.r_[np.ones(len(good)), np.full(len(bad), 1 / 16)]
    res = solve(world.nominal, Observations(q, pt, weight=wts), "offsets,tcp", "unknown")
    plain = solve(world.nominal, Observations(q, pt), "offsets,tcp", "unknown")
    assert res.trusted, res.failure
    assert res.sigma_m == pytest.approx(NOISE, rel=0.25)
    assert plain.sigma_m > 1.8 * NOISE
    for n in ("offset.j2", "offset.j3"):
        p = res.parameters[n]
        assert abs(p.value - world.truth.param(n)) < 4 * p.std
        assert p.std < plain.parameters[n].std
    with pytest.raises(SolverInputError, match="weight"):
        Observations(q, pt, weight=np.r_[wts[:-1], 0.0])


def test_cli_weight_and_fixture_columns(world, tmp_path):
    obs = fixture_data(world, np.random.default_rng(4), 10)
    w = np.where(np.arange(len(obs)) % 2, 1.0, 0.5)
    lines = ["q1,q2,q3,q4,q5,q6,point,fixture,weight"]
    lines += [",".join(f"{v:.12f}" for v in q) + f",{p},{f},{wt}"
              for q, p, f, wt in zip(obs.q, obs.point, obs.fixture, w, strict=True)]
    (tmp_path / "s.csv").write_text("\n".join(lines) + "\n")
    d_mm = float(np.linalg.norm(world.points["A"].position - world.points["B"].position)) * 1e3
    p = station_proc("solve", "--model", "ur5e", "--samples", "s.csv", "--identify", "offsets,dh,tcp",
                     "--distance", f"A,B={d_mm:.6f}mm", "--out", "r.json", cwd=tmp_path)
    assert p.code == 0, p.err
    doc = json.loads((tmp_path / "r.json").read_text())
    assert sorted(c["fixture"] for c in doc["constraints"]) == ["1", "2"]
    assert {"point.A@1.x", "point.B@2.z"} <= set(doc["parameters"])
    assert doc["settings"]["fixtures"] == ["1", "2"] and doc["settings"]["weighted"] is True
    (tmp_path / "bad.csv").write_text("q1,q2,q3,q4,q5,q6,weight\n0,0,0,0,0,0,-1\n")
    p = station_proc("solve", "--model", "ur5e", "--samples", "bad.csv", cwd=tmp_path, timeout=60)
    assert p.code == 2 and "bad.csv:2: column 'weight'" in p.err and p.err.count("\n") == 1, p.err
