"""ISO 9283 characteristics (station.performance.iso9283): the formulas against a hand calculation, against the
standard's definitions on synthetic data with a known barycentre and spread, and the confidence intervals'
coverage over Monte Carlo sets (the sampling error of each coverage is binomial: bands of 3.3 standard errors,
a false alarm about once in a thousand runs)."""

import math

import numpy as np
import pytest
from scipy import stats

from station.kinematics import se3
from station.performance import iso9283 as iso

MM = 1e-3


def _rotx(a):  # pose vector rotated by a about the base x axis
    return [0.0, 0.0, 0.0, a, 0.0, 0.0]


def test_hand_calculation():
    """Four cycles, numbers small enough to check on paper (mm and mrad)."""
    P = np.array([[1, 0, 0], [3, 0, 0], [2, 2, 0], [2, -2, 0]], float) * MM  # attained positions of pose A
    a = np.array([1, 3, 2, 2], float) * 1e-3  # attained rotations about x (rad); commanded 0
    attained = np.column_stack([P, a, np.zeros(4), np.zeros(4)])
    out = iso.pose_characteristics(np.zeros(6), attained)
    # barycentre (2, 0, 0) mm; AP_p = |(2, 0, 0) - 0| = 2 mm
    assert out["barycentre"] == pytest.approx([2 * MM, 0, 0], abs=1e-15)
    assert out["AP_p"] == pytest.approx(2 * MM, rel=1e-12)
    assert (out["AP_x"], out["AP_y"], out["AP_z"]) == pytest.approx((2 * MM, 0, 0), abs=1e-15)
    # l = 1, 1, 2, 2 mm: l̄ = 1.5, S_l = sqrt((0.25 * 4) / 3) = 0.57735; RP_l = 1.5 + 3 * 0.57735 = 3.23205 mm
    assert out["l_mean"] == pytest.approx(1.5 * MM, rel=1e-12)
    assert out["S_l"] == pytest.approx(math.sqrt(1 / 3) * MM, rel=1e-12)
    assert out["RP_l"] == pytest.approx((1.5 + 3 * math.sqrt(1 / 3)) * MM, rel=1e-12)
    # orientation: ā = 2 mrad -> AP_a = 2 mrad; S_a = sqrt((1 + 1 + 0 + 0) / 3) mrad -> RP_a = 3 S_a = 2.4495 mrad
    assert out["AP_a"] == pytest.approx(2e-3, rel=1e-6) and abs(out["AP_b"]) < 1e-12
    assert out["RP_a"] == pytest.approx(3 * math.sqrt(2 / 3) * 1e-3, rel=1e-6)
    # AP_x's 95 % interval: 2 mm +- t(0.975, 3) * s / sqrt(4), s = sqrt((1 + 1 + 0 + 0) / 3) mm = 0.8165 mm
    half = 3.182446305284263 * math.sqrt(2 / 3) / 2 * MM
    assert out["AP_x_ci"] == pytest.approx([2 * MM - half, 2 * MM + half], rel=1e-9)
    # RP_a's interval: 3 S_a sqrt(3 / chi2(0.975, 3)) .. 3 S_a sqrt(3 / chi2(0.025, 3)) = 0.5665 S .. 3.7257 S (x 3)
    s_a = math.sqrt(2 / 3) * 1e-3
    assert out["RP_a_ci"] == pytest.approx([3 * s_a * math.sqrt(3 / 9.348404), 3 * s_a * math.sqrt(3 / 0.2157953)],
                                           rel=1e-5)

    # vAP: the same cluster and one 0.5 mm higher -> the barycentres are 0.5 mm apart
    other = attained.copy()
    other[:, 2] += 0.5 * MM
    other[:, 3] += 0.4e-3  # and 0.4 mrad more about x
    with pytest.raises(iso.IsoError, match="at least 4"):  # fewer than 4 cycles in a direction
        iso.vap_characteristics(np.zeros(6), {"-x": attained[:3], "-z": other})
    vap = iso.vap_characteristics(np.zeros(6), {"-x": attained, "-z": other})
    assert vap["vAP_p"] == pytest.approx(0.5 * MM, rel=1e-12) and vap["vAP_a"] == pytest.approx(0.4e-3, rel=1e-6)
    assert vap["directions"] == {"-x": 4, "-z": 4}

    # distance between pose A and pose B (commanded 10 mm away along x, attained 12 mm away, every cycle):
    # D = 11, 9, sqrt(104), sqrt(104) mm; D̄ = (20 + 2 sqrt(104)) / 4 = 10.0990 mm; AD_p = D̄ - 10 mm
    B = np.tile([12 * MM, 0, 0, 0, 0, 0], (4, 1))
    dist = iso.distance_characteristics(np.zeros(6), [10 * MM, 0, 0, 0, 0, 0], attained, B)
    D = np.array([11, 9, math.sqrt(104), math.sqrt(104)])
    assert dist["D_c"] == pytest.approx(10 * MM) and dist["AD_p"] == pytest.approx((D.mean() - 10) * MM, rel=1e-12)
    # RD_p = 3 S_D, S_D = sqrt(sum((D - D̄)^2) / 3)
    assert dist["RD_p"] == pytest.approx(3 * math.sqrt(np.sum((D - D.mean()) ** 2) / 3) * MM, rel=1e-12)
    # AD_x = mean(x1 - x2) - (xc1 - xc2) = (2 - 12) - (0 - 10) = 0 mm; AD_a = mean(a1 - a2) = 2 mrad
    assert abs(dist["AD_x"]) < 1e-15 and dist["AD_a"] == pytest.approx(2e-3, rel=1e-6)


def test_orientation_deviation_is_the_small_angle_difference():
    """The rotation vector of R_j R_c^T is the standard's (a_j - a_c, b_j - b_c, c_j - c_c) to first order."""
    c = np.array([0.3, 0.1, 0.5, 0.4, -1.2, 0.7])
    small = np.array([2e-4, -1e-4, 3e-4])
    Rj = se3.rotvec_to_matrix(small) @ se3.rotvec_to_matrix(c[3:])
    att = np.concatenate([c[:3], se3.matrix_to_rotvec(Rj)])[None]
    assert iso.deviations(c, att)[0] == pytest.approx(small, abs=1e-12)


def test_known_barycentre_and_spread():
    """Many cycles drawn around a known barycentre with a known spread: every figure lands on the value the
    standard's definition gives for that population, inside its interval."""
    rng = np.random.default_rng(11)
    n = 3000
    c = np.array([0.5, -0.2, 0.4, 0.0, 0.0, 0.0])
    offset = np.array([0.12, -0.05, 0.03]) * MM  # the robot's systematic error at this pose
    sigma = 0.02 * MM  # isotropic repeatability, per axis
    sig_r = np.array([3e-5, 5e-5, 1e-5])  # rad, per angle
    bias_r = np.array([1e-4, -2e-4, 0.5e-4])
    pos = c[:3] + offset + rng.normal(0, sigma, (n, 3))
    rot = bias_r + rng.normal(0, 1, (n, 3)) * sig_r  # rotation vectors about the commanded (identity) orientation
    out = iso.pose_characteristics(c, np.column_stack([pos, rot]))
    assert out["AP_p_ci"][0] <= np.linalg.norm(offset) <= out["AP_p_ci"][1]
    assert out["AP_p"] == pytest.approx(np.linalg.norm(offset), abs=3 * sigma * math.sqrt(3 / n))
    rp_true = (2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi)) * sigma  # E|Y| + 3 SD|Y|, Y ~ N(0, s^2 I)
    assert iso.rp_floor(sigma) == pytest.approx(rp_true, rel=1e-12)
    assert out["RP_l_ci"][0] <= rp_true <= out["RP_l_ci"][1]
    assert out["RP_l"] == pytest.approx(rp_true, rel=0.03)
    for k, an in enumerate("abc"):
        assert out[f"AP_{an}_ci"][0] <= bias_r[k] <= out[f"AP_{an}_ci"][1]
        assert out[f"RP_{an}_ci"][0] <= 3 * sig_r[k] <= out[f"RP_{an}_ci"][1]


def _coverage(hits: int, m: int, level: float = 0.95, conservative: bool = False) -> None:
    se = math.sqrt(level * (1 - level) / m)
    rate = hits / m
    assert rate >= level - 3.3 * se, (rate, level)
    if not conservative:
        assert rate <= level + 3.3 * se, (rate, level)


def test_interval_coverage_of_the_means_and_spreads():
    """AP_x (t), AP_p (Hotelling ellipsoid: at least the level), RP_a (chi-square), vAP (Bonferroni: at least),
    AD_p and RD_p over 400 sets of 30 cycles from known populations."""
    rng = np.random.default_rng(2024)
    m, n = 400, 30
    c = np.zeros(6)
    offset, scale = np.array([0.04, 0.0, -0.02]) * MM, np.array([0.03, 0.01, 0.02]) * MM
    sig_a = 4e-5
    h = {k: 0 for k in ("AP_x", "AP_p", "RP_a", "vAP_p", "AD_p", "RD_p")}
    for _ in range(m):
        a = np.column_stack([offset + rng.normal(0, 1, (n, 3)) * scale, rng.normal(0, sig_a, n), np.zeros((n, 2))])
        out = iso.pose_characteristics(c, a, rp_ci=False)
        h["AP_x"] += out["AP_x_ci"][0] <= offset[0] <= out["AP_x_ci"][1]
        h["AP_p"] += out["AP_p_ci"][0] <= np.linalg.norm(offset) <= out["AP_p_ci"][1]
        h["RP_a"] += out["RP_a_ci"][0] <= 3 * sig_a <= out["RP_a_ci"][1]
        b = a.copy()
        b[:, :3] = offset + rng.normal(0, 1, (n, 3)) * scale  # a second direction with the same barycentre
        vap = iso.vap_characteristics(c, {"x": a, "y": b})
        h["vAP_p"] += vap["vAP_p_ci"][0] <= 0.0 <= vap["vAP_p_ci"][1]
        far = np.column_stack([np.array([0.2, 0.0, 0.0]) + rng.normal(0, 1, (n, 3)) * scale, np.zeros((n, 3))])
        d = iso.distance_characteristics(c, [0.2, 0, 0, 0, 0, 0], a, far)
        # the population distance: |offset + e1 - e2 - (0.2, 0, 0)| averaged: to first order 0.2 - offset_x
        h["AD_p"] += d["AD_p_ci"][0] <= -offset[0] <= d["AD_p_ci"][1]
        h["RD_p"] += d["RD_p_ci"][0] <= 3 * math.sqrt(2) * scale[0] <= d["RD_p_ci"][1]
    for k in ("AP_x", "RP_a", "AD_p", "RD_p"):
        _coverage(h[k], m)
    for k in ("AP_p", "vAP_p"):
        _coverage(h[k], m, conservative=True)


@pytest.mark.slow  # 2 x 200 sets with the RP_l simulation: ~60 s
@pytest.mark.parametrize("scale", [(1.0, 1.0, 1.0), (3.0, 1.0, 0.3)], ids=["isotropic", "anisotropic"])
def test_rp_interval_coverage(scale):
    """RP_l's interval covers the population value E|Y - μ| + 3 SD|Y - μ| at the stated level (normal scatter)."""
    rng = np.random.default_rng(7)
    cov = np.diag(np.square(scale)) * (0.01 * MM) ** 2
    truth = float(iso._rp_population(cov))
    z = rng.standard_normal((2_000_000, 3)) * np.sqrt(np.diag(cov))  # the population value, independently
    lz = np.linalg.norm(z, axis=1)
    assert truth == pytest.approx(lz.mean() + 3 * lz.std(), rel=2e-3)
    m, hits = 200, 0
    for _ in range(m):
        lo, hi = iso.rp_interval(rng.normal(0, 1, (30, 3)) * np.sqrt(np.diag(cov)))
        hits += lo <= truth <= hi
    _coverage(hits, m)


def test_t_factor_and_chi_square_are_the_tables():
    """The interval constants against the printed tables (t: 2.045 for 29 dof; chi-square 16.047 / 45.722)."""
    m, lo, hi = iso.mean_interval(np.array([-1.0, 1.0] * 15))
    assert (hi - m) == pytest.approx(2.0452 * math.sqrt(30 / 29) / math.sqrt(30), rel=1e-4)
    v, lo, hi = iso.sd3_interval(np.array([-1.0, 1.0] * 15))
    s = math.sqrt(30 / 29)
    assert (lo, hi) == pytest.approx((3 * s * math.sqrt(29 / 45.722), 3 * s * math.sqrt(29 / 16.047)), rel=1e-4)
    assert stats.t.ppf(0.975, 29) == pytest.approx(2.0452, rel=1e-4)
