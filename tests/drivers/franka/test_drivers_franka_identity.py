"""``station.drivers.franka.identity``: the pose the controller reports (``O_T_EE``, column-major as libfranka sends
it) against the station's FR3 model with the end effector set in Desk (``F_T_EE``), the controller's side computed
here from Franka's published DH table (Craig convention, flange 0.107 m)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from station.drivers.franka.identity import check_reported_pose, column_major, with_flange_to_ee

from station.kinematics import load_model
from station.robot.errors import IdentityMismatch

# Franka Robotics, "Robot and interface specifications", Denavit-Hartenberg parameters: a, d, alpha per joint
DH = [(0, 0.333, 0), (0, 0, -np.pi / 2), (0, 0.316, np.pi / 2), (0.0825, 0, np.pi / 2),
      (-0.0825, 0.384, -np.pi / 2), (0, 0, np.pi / 2), (0.088, 0, np.pi / 2)]
FLANGE = 0.107


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def _t(x=0.0, z=0.0):
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def franka_fk(q) -> np.ndarray:
    T = np.eye(4)
    for (a, d, alpha), theta in zip(DH, q, strict=True):
        T = T @ _rx(alpha) @ _t(x=a) @ _rz(theta) @ _t(z=d)
    return T @ _t(z=FLANGE)


HAND = _rz(-np.pi / 4) @ _t(z=0.1034)  # Franka Hand's default F_T_EE


def state_at(q, O_T_EE):
    return SimpleNamespace(q=list(q), O_T_EE=list(O_T_EE.T.ravel()), F_T_EE=list(HAND.T.ravel()))


def test_reported_pose_matches_the_fr3_model():
    model = load_model("fr3")
    q = np.array([0.1, -0.5, 0.2, -2.0, 0.3, 1.5, 0.4])
    dp, dr = check_reported_pose("franka://x", model, state_at(q, franka_fk(q) @ HAND))
    assert dp < 1e-9 and dr < 1e-9
    assert np.allclose(with_flange_to_ee(model, HAND).fk(q), franka_fk(q) @ HAND, atol=1e-12)
    assert np.array_equal(column_major(list(HAND.T.ravel())), HAND)


def test_another_end_effector_is_refused():
    model = load_model("fr3")
    q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    off = franka_fk(q) @ HAND @ _t(z=0.001)  # the controller's end effector 1 mm longer than Desk's
    with pytest.raises(IdentityMismatch, match=r"^franka://x: the controller puts the end effector 1.000 mm"):
        check_reported_pose("franka://x", model, state_at(q, off))
