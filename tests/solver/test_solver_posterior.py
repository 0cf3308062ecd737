"""``station.solver.posterior``: the consider covariance checked by Monte Carlo on a linear problem with priors,
the Student-t factor against scipy, and the identified set."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from station.solver.posterior import MAX_RATIO, decide, posterior, spd_inverse, t_factor


@pytest.mark.parametrize("dof", [1, 2, 3, 7, 29, 100, 200, 201, 300, 5000])
def test_t_factor_keeps_three_sigma_coverage(dof):
    p = 2 * stats.norm.sf(3.0)
    assert t_factor(dof) == pytest.approx(stats.t.ppf(1 - p / 2, dof) / 3.0, rel=1e-6)
    assert t_factor(0) == math.inf


def test_spd_inverse_of_a_badly_scaled_matrix():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 4)) * np.array([1e-6, 1.0, 1e3, 1.0])  # columns in very different units
    H = A.T @ A
    d = np.sqrt(np.diag(H))  # checked in the units of each column (the raw product spans 18 decades)
    assert np.allclose((spd_inverse(H) * np.outer(d, d)) @ (H / np.outer(d, d)), np.eye(4), atol=1e-9)
    S = np.array([[1.0, 1.0], [1.0, 1.0]])  # singular: the pseudo-inverse
    assert np.allclose(spd_inverse(S), np.linalg.pinv(S))


def test_consider_covariance_is_the_spread_of_the_estimates():
    """Estimate columns 0..2 with column 3 held at nominal (0) while its truth varies with its prior: the
    covariance ``posterior`` reports is what the maximum a-posteriori estimates scatter by around the truth."""
    rng = np.random.default_rng(7)
    m, sigma = 30, 0.01
    B = rng.normal(size=(m, 4))
    prior = np.array([0.05, 0.02, np.inf, 0.03])  # column 2: a nuisance unknown (no prior)
    cols, kept = [0, 1, 2], [3]
    post = posterior(B.T @ B, cols, kept, sigma, prior)
    H = B[:, cols].T @ B[:, cols] / sigma**2 + np.diag([1 / 0.05**2, 1 / 0.02**2, 0.0])
    n = 20000
    x = np.column_stack([rng.normal(0, 0.05, n), rng.normal(0, 0.02, n), rng.normal(0, 1.0, n),
                         rng.normal(0, 0.03, n)])
    y = x @ B.T + rng.normal(0, sigma, (n, m))
    est = np.linalg.solve(H, B[:, cols].T @ y.T / sigma**2).T  # MAP with column 3 at nominal
    err = est - x[:, cols]
    emp = np.cov(err.T)
    assert np.allclose(np.sqrt(np.diag(emp)), post.std, rtol=0.03)
    assert np.allclose(emp, post.cov, atol=0.05 * post.std.max() ** 2)
    # without the kept column's prior the reported std would be too small: the consider part matters
    assert (post.std > np.sqrt(np.diag(post.info_inv)) * 1.05).any()


def test_decide_drops_what_the_data_do_not_determine():
    rng = np.random.default_rng(3)
    B = rng.normal(size=(40, 3))
    B[:, 2] *= 1e-4  # this parameter barely moves the residuals
    prior = np.array([0.01, 0.01, 0.01])
    d = decide(B.T @ B, [0, 1, 2], [0, 1, 2], [], 0.001, prior, np.ones(3))
    assert d.accepted == [0, 1] and set(d.weak) == {2}
    std_would_have, prior_std = d.weak[2]
    assert std_would_have > MAX_RATIO * prior_std
    # a max_std at the tool tighter than what the data give drops the rest too
    d = decide(B.T @ B, [0, 1], [0, 1], [], 0.001, prior, np.ones(3), max_std=1e-6)
    assert d.accepted == []
