"""Closed-form TCP methods on simulated flange poses with a hidden tool and 20 um noise."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from station.kinematics import se3
from station.solver import SolverInputError, tcp_circle_fit, tcp_from_flange_poses, tcp_scara_4point

NOISE = 20e-6


def _flange_poses(t, c, rotations, rng):
    """Flange pose (x, y, z, rotation vector) with the tool tip t on point c (+ noise)."""
    R = rotations.as_matrix()
    p = c - R @ t + rng.normal(0, NOISE, (len(R), 3))
    return np.column_stack([p, rotations.as_rotvec()])


def test_tcp_from_flange_poses_recovers_tool_and_point():
    rng = np.random.default_rng(1)
    t, c = np.array([0.012, -0.031, 0.154]), np.array([0.45, -0.2, 0.1])
    rot = Rotation.from_euler("xyz", np.column_stack([rng.uniform(-0.5, 0.5, 12) + np.pi, rng.uniform(-0.5, 0.5, 12),
                                                      rng.uniform(-np.pi, np.pi, 12)]))
    poses = _flange_poses(t, c, rot, rng)
    fit = tcp_from_flange_poses(poses)
    assert fit.rank == 6 and not fit.unidentifiable
    assert np.all(np.abs(fit.tcp - t) < 4 * fit.tcp_std)
    assert np.all(np.abs(fit.point - c) < 4 * fit.point_std)
    assert fit.rms_m < 3 * NOISE * np.sqrt(3)
    # the same as 4x4 matrices
    T = se3.pose_to_matrix(poses)
    np.testing.assert_allclose(tcp_from_flange_poses(T).tcp, fit.tcp, atol=1e-12)


def test_rotations_about_one_axis_leave_the_tool_length_unidentifiable():
    rng = np.random.default_rng(2)
    t, c = np.array([0.03, 0.01, 0.08]), np.array([0.3, 0.1, 0.0])
    rot = Rotation.from_euler("z", rng.uniform(-2, 2, (8, 1)))
    fit = tcp_from_flange_poses(_flange_poses(t, c, rot, rng))
    assert fit.rank == 5
    assert "tcp.z" in fit.unidentifiable and np.isnan(fit.tcp[2])
    assert np.all(np.abs(fit.tcp[:2] - t[:2]) < 4 * fit.tcp_std[:2])


def test_scara_4point_seed_001():
    rng = np.random.default_rng(3)
    t, c = np.array([0.025, -0.012, 0.06]), np.array([0.4, 0.15, 0.02])
    theta = rng.uniform(-2.5, 2.5, 6)
    R = Rotation.from_euler("z", theta[:, None]).as_matrix()
    P = c - R @ t + rng.normal(0, NOISE, (6, 3))
    fit = tcp_scara_4point(P, theta)
    assert np.all(np.abs(fit.tcp[:2] - t[:2]) < 4 * fit.tcp_std[:2])
    assert "point_z" in fit.unidentifiable["tcp.z"] and np.isnan(fit.tcp[2])
    fit = tcp_scara_4point(P, theta, point_z=c[2])
    assert not fit.unidentifiable
    assert abs(fit.tcp[2] - t[2]) < 4 * fit.tcp_std[2]
    with pytest.raises(SolverInputError, match="at least 4"):
        tcp_scara_4point(P[:3], theta[:3])


def test_circle_fit_seed_003():
    rng = np.random.default_rng(4)
    tip, t = np.array([0.2, 0.3, 0.05]), np.array([0.018, 0.009, 0.0])
    theta = np.linspace(-2.5, 2.5, 15)
    R = Rotation.from_euler("z", theta[:, None]).as_matrix()
    P = tip - R @ t + rng.normal(0, NOISE, (15, 3))
    fit = tcp_circle_fit(P, theta)
    assert abs(fit.radius - np.linalg.norm(t)) < 4 * NOISE
    assert np.linalg.norm(fit.centre[:2] - tip[:2]) < 4 * NOISE
    assert np.linalg.norm(fit.tcp[:2] - t[:2]) < 4 * NOISE
    assert fit.rms_m < 3 * NOISE
    with pytest.raises(SolverInputError, match="collinear"):
        tcp_circle_fit(np.column_stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)]))
