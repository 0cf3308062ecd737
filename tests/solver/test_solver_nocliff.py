"""No cliffs in the estimator: a parameter the data determine to within its prior is estimated (with its
posterior std and the prior's share of it), and one touch more or less or another noise draw never flips a
trusted result into a failure.

The case that failed: UR5e, a known point, a known TCP 1.4 mm off the last axis, 10 touches, zero offsets of up
to 2 deg. Joint 6's offset is seen only through that small lever: its std is ~0.3 deg, at the old "poorly
observed" line (0.3 x its 1 deg tolerance). It was kept at nominal (its 1.5-1.7 deg error left in the model) or
the identified set went round in circles ("did not settle", exit 1), depending on the noise draw.
Ground truth: the simulated robot (``simulate.touch_observations``: IK of the true model, Gaussian tip noise)."""

import math

import numpy as np
import pytest

from station.kinematics import load_model
from station.solver import Observations, solve
from station.solver.simulate import noisy_q, touch_observations

POINT = np.array([0.45, 0.15, 0.25])
NOISE = 20e-6
ROBOTS = (3, 4, 10, 11)  # the draws that failed: 3 did not settle, 4/10/11 kept joint 6 at nominal


def nominal():
    return load_model("ur5e").with_params({"tcp.x": 0.0014, "tcp.z": 0.1})


def robot(seed: int):
    rng = np.random.default_rng(seed)
    offs = {f"offset.j{j}": float(np.radians(rng.uniform(-2, 2))) for j in range(1, 7)}
    truth = nominal().with_params(offs)
    obs = touch_observations(truth, {"A": POINT}, 10, rng, noise=NOISE)
    return truth, offs, obs, rng


def check(res, offs, where=""):
    assert res.trusted, (where, res.failure)
    for n, v in offs.items():
        p = res.parameters[n]
        assert p.identifiable, (where, n, p.reason)
        assert abs(p.value - v) < 4 * p.std, (where, n, math.degrees(p.value - v), math.degrees(p.std))


@pytest.mark.parametrize("seed", ROBOTS)
def test_ur5e_known_point_off_axis_tcp_joint6_at_the_old_line_is_estimated(seed):
    truth, offs, obs, _ = robot(seed)
    res = solve(nominal(), obs, "offsets", {"A": POINT})
    check(res, offs)
    p6 = res.parameters["offset.j6"]
    assert 0.22 < math.degrees(p6.std) < 0.4  # the case of the issue: ~0.3 deg
    # how much the prior contributed: its share of what is known of joint 6 (a tenth here), ~0 for joint 2; for
    # one parameter that share is its posterior variance over the prior's (the reported std adds the Student-t
    # factor and what the other offsets leave uncertain, hence the tolerance)
    assert 0.03 < p6.prior_share < 0.5 and res.parameters["offset.j2"].prior_share < 1e-3
    assert p6.prior_share == pytest.approx(p6.std**2 / p6.prior_std**2, rel=0.35)


@pytest.mark.parametrize("seed", ROBOTS)
def test_a_touch_more_or_less_or_another_noise_draw_never_flips_trust(seed):
    truth, offs, obs, rng = robot(seed)
    n = len(obs)
    for k in range(n):  # leave one touch out
        keep = np.arange(n) != k
        res = solve(nominal(), Observations(obs.q[keep], obs.point[keep]), "offsets", {"A": POINT})
        check(res, offs, f"without touch {k}")
    more = touch_observations(truth, {"A": POINT}, 1, rng, noise=NOISE)  # one touch more
    res = solve(nominal(), Observations(np.vstack([obs.q, more.q]), np.r_[obs.point, more.point]), "offsets",
                {"A": POINT})
    check(res, offs, "one more")
    targets = np.broadcast_to(POINT, (n, 3))
    for d in range(6):  # the same poses, other noise draws
        q = noisy_q(truth, obs.q, targets, NOISE, np.random.default_rng(100 + d))
        check(solve(nominal(), Observations(q, obs.point), "offsets", {"A": POINT}), offs, f"noise draw {d}")


@pytest.mark.slow
def test_posterior_std_at_the_line_covers_the_truth_over_robots_drawn_from_the_prior():
    """Monte Carlo coverage: 120 robots with offsets drawn from the prior (N(0, 1 deg)), 10 touches each; the
    offsets' z = (estimate - truth) / std must be standard normal where joint 6 sits at the line."""
    z, std6 = [], []
    for t in range(120):
        rng = np.random.default_rng(1000 + t)
        offs = {f"offset.j{j}": float(np.radians(rng.normal(0.0, 1.0))) for j in range(1, 7)}
        truth = nominal().with_params(offs)
        obs = touch_observations(truth, {"A": POINT}, 10, rng, noise=NOISE)
        res = solve(nominal(), obs, "offsets", {"A": POINT})
        assert res.trusted, res.failure
        z.append([(res.parameters[n].value - v) / res.parameters[n].std for n, v in offs.items()])
        std6.append(math.degrees(res.parameters["offset.j6"].std))
    z = np.array(z)
    assert 0.2 < np.median(std6) < 0.45
    inside = np.mean(np.abs(z) < 1.96, axis=0)  # 95 % within 4 binomial std (0.02 each at n = 120)
    assert np.all(np.abs(inside - 0.95) < 4 * math.sqrt(0.95 * 0.05 / len(z))), inside
    assert np.all(np.abs(z) < 5), np.abs(z).max(axis=0)
    ms = np.mean(z**2, axis=0)  # mean z^2 ~ 1 (chi-square, 120 dof: 0.1 % bands 0.66 .. 1.45)
    assert np.all((ms > 0.66) & (ms < 1.45)), ms
