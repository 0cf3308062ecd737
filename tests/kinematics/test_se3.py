"""Rotation conversions (numpy, no scipy at start-up) against scipy's Rotation as the independent reference:
random rotations, tiny angles, angles at and near 180 deg, gimbal lock, single and batched inputs."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from station.kinematics import se3


def _rotvecs(rng, n=3000):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, np.pi, (n, 1))
    angle[:10] = 10.0 ** -rng.uniform(6, 14, (10, 1))  # tiny: the series branch
    angle[10:20] = np.pi - 10.0 ** -rng.uniform(3, 12, (10, 1))  # near 180 deg: the axis from the symmetric part
    angle[20:23] = np.pi
    rv = axis * angle
    rv[23] = 0.0
    return rv


def test_rotvec_matches_scipy_both_ways():
    rv = _rotvecs(np.random.default_rng(1))
    R_ref = Rotation.from_rotvec(rv).as_matrix()
    assert np.abs(se3.rotvec_to_matrix(rv) - R_ref).max() < 1e-14
    back = se3.matrix_to_rotvec(R_ref)
    assert np.linalg.norm(back, axis=1).max() <= np.pi + 1e-12
    # at 180 deg +axis and -axis are the same rotation: compare rotations, and vectors away from it
    assert np.abs(se3.rotvec_to_matrix(back) - R_ref).max() < 1e-14
    away = np.linalg.norm(rv, axis=1) < np.pi - 1e-3
    assert np.abs(back[away] - Rotation.from_matrix(R_ref[away]).as_rotvec()).max() < 1e-12
    assert np.allclose(se3.matrix_to_rotvec(R_ref[30]), Rotation.from_matrix(R_ref[30]).as_rotvec(), atol=1e-14)


def test_rpy_matches_scipy_and_gimbal_lock_stays_exact():
    rng = np.random.default_rng(2)
    rpy = rng.uniform(-np.pi, np.pi, (3000, 3))
    rpy[:, 1] /= 2
    rpy[:4, 1] = [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-12, -np.pi / 2 + 1e-12]
    R_ref = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    assert np.abs(se3.rpy_to_matrix(rpy) - R_ref).max() < 1e-14
    back = se3.matrix_to_rpy(R_ref)
    # within 1e-9 of the lock roll is set to 0: the decomposition is exact to the order of that cos(pitch)
    assert np.abs(se3.rpy_to_matrix(back) - R_ref).max() < 1e-11
    assert np.abs(back[4:] - rpy[4:]).max() < 1e-9
    assert se3.rpy_to_matrix(rpy[7]).shape == (3, 3)


@pytest.mark.parametrize("seed", range(3))
def test_orientation_error_is_the_world_frame_rotation(seed):
    R1, R2 = Rotation.random(2, random_state=seed).as_matrix()
    assert np.allclose(se3.orientation_error(R1, R2), Rotation.from_matrix(R1 @ R2.T).as_rotvec(), atol=1e-13)


def test_no_scipy_for_the_kinematics_at_import():
    import subprocess
    import sys

    code = "import sys, station.kinematics.se3; print('scipy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "False"


def test_frame_with_z_is_a_proper_rotation_onto_z_and_roll_turns_about_it():
    rng = np.random.default_rng(4)
    dirs = [*rng.normal(size=(200, 3)), np.array([1.0, 0, 0]), np.array([0, 0, -3.0]), np.array([0.95, 0.3, 0])]
    for z in dirs:
        roll = rng.uniform(-np.pi, np.pi)
        R = se3.frame_with_z(z, roll)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R[:, 2], z / np.linalg.norm(z), atol=1e-12)
        # the roll is a turn about the frame's own z (scipy's rotation, not ours)
        turned = se3.frame_with_z(z) @ Rotation.from_euler("z", roll).as_matrix()
        assert np.allclose(R, turned, atol=1e-12)
