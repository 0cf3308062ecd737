"""``station.solver.noise``: encoder quantisation read from the readings, and the touch noise whitening checked
by Monte Carlo (whitened residuals have covariance sigma^2 I)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from station.kinematics import load_model
from station.solver.noise import NoiseModel, joint_noise_of, quantisation, resolution_of


def test_quantisation_separates_shared_ticks_from_independent_ones():
    tick = 2 * math.pi / 4096
    res = np.array([tick / math.sqrt(12), 0.0])
    q = np.array([[10, 0.1], [10, 0.2], [11, 0.3], [12, 0.4]], dtype=float)
    q[:, 0] *= tick
    var, groups = quantisation(q, res)
    assert var[:, 0].tolist() == [0.0, 0.0, res[0] ** 2, res[0] ** 2]  # touches 0, 1 share tick 10
    assert len(groups) == 1 and groups[0][0] == 0 and groups[0][1].tolist() == [True, True, False, False]
    assert not var[:, 1].any()  # no encoder
    off = q.copy()
    off[0, 0] += 0.3 * tick  # one reading off the grid: interpolated, no quantisation term at all
    assert not quantisation(off, res)[0].any()


def test_encoder_resolution_and_joint_noise_per_joint():
    m = load_model("omx")  # Dynamixel servos: 4096 counts per turn
    r = resolution_of(m)
    assert r == pytest.approx(np.full(4, 2 * math.pi / 4096 / math.sqrt(12)), rel=1e-9)
    assert joint_noise_of(m, None).tolist() == [0.0] * 4
    assert joint_noise_of(m, 1e-4).tolist() == [1e-4] * 4
    with pytest.raises(ValueError, match="joint noise must be >= 0"):
        joint_noise_of(m, [-1e-4, 0, 0, 0])


def test_isotropic_sigma_is_the_rms_per_degree_of_freedom():
    nm = NoiseModel(None, np.zeros(6), 10)
    r = np.random.default_rng(0).normal(0, 2e-5, 30)
    assert nm.fit_sigma(r, 24) == pytest.approx(math.sqrt(r @ r / 24))
    assert nm.residual(r) is not r and np.allclose(nm.residual(r), r)


def test_whitened_residuals_have_covariance_sigma_squared():
    rng = np.random.default_rng(4)
    n, sigma_iso = 4000, 20e-6
    var_q = np.full(6, (50e-6) ** 2)  # rad^2
    Jq = rng.normal(0, 0.5, (n, 3, 6))  # m/rad
    C = sigma_iso**2 * np.eye(3) + np.einsum("nij,j,nkj->nik", Jq, var_q, Jq)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 3))).ravel()
    nm = NoiseModel(Jq, var_q, n)
    assert nm.joint
    sigma = nm.declare(sigma_iso)
    w = nm.residual(r).reshape(n, 3)
    cov = np.cov(w.T)
    assert np.allclose(np.diag(cov), sigma**2, rtol=0.08) and abs(cov[0, 1]) < 0.08 * sigma**2
    # and the maximum-likelihood fit of (f, sigma) from the residuals finds about the same sigma
    assert nm.fit_sigma(r, 3 * n) == pytest.approx(sigma, rel=0.05)
