"""Franka Research 3 motion limits, as Franka documents them and libfranka encodes them (SI units).

Sources: Franka Robotics, "Robot and interface specifications", section "Limits for Franka Research 3"
(frankarobotics.github.io/docs/control_parameters.html), and libfranka 0.21 ``include/franka/rate_limiting.h``
(``kMaxJointJerk``, ``kMaxJointAcceleration``, ``kMaxTranslational*``, ``kMaxRotational*``,
``computeUpperLimitsJointVelocity``/``computeLowerLimitsJointVelocity``, which cite that section) and
``src/joint_velocity_limits.cpp`` (the same envelope read from the ``<position_based_velocity_limits>`` of the
URDF the robot serves, system image >= 5.9). A joint's velocity limit depends on its position: near the end
of its range it must still be able to stop, ``|dq| <= -offset + sqrt(2 * decel * distance to the limit)``."""

from __future__ import annotations

import numpy as np

Q_MIN = np.array([-2.7501, -1.7918, -2.9065, -3.0481, -2.8101, 0.54092, -3.0196])  # rad
Q_MAX = np.array([2.7501, 1.7918, 2.9065, -0.1458, 2.8101, 4.5205, 3.0196])  # rad
DQ_MAX = np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])  # rad/s
DDQ_MAX = np.full(7, 10.0)  # rad/s^2
DDDQ_MAX = np.full(7, 5000.0)  # rad/s^3
TAU_MAX = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])  # N m
DTAU_MAX = np.full(7, 1000.0)  # N m/s
# the position-based envelope: velocity offset (rad/s) and deceleration (rad/s^2) per joint; libfranka's
# formula has the form sqrt(K * (q_max - q)) with K = 2 * decel (12.0, 5.17, 7.0, 8.0, 34.0, 11.0, 34.0)
V_OFFSET = np.array([0.30, 0.20, 0.20, 0.30, 0.35, 0.35, 0.35])
DECEL = np.array([6.0, 2.585, 3.5, 4.0, 17.0, 5.5, 17.0])
TOLERANCE = 1e-3  # rad/s: kJointVelocityLimitsTolerance (kLimitEps, no packet loss on an FR3)
# Cartesian limits of the end effector (translation m/s, m/s^2, m/s^3; rotation rad/s, rad/s^2, rad/s^3)
CARTESIAN = {"v": 3.0, "a": 9.0, "j": 4500.0, "w": 2.5, "dw": 17.0, "ddw": 8500.0}


def velocity_envelope(q) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper joint velocity limits (rad/s) at positions ``q`` (..., 7)."""
    q = np.asarray(q, float)
    up = np.minimum(DQ_MAX, np.maximum(0.0, -V_OFFSET + np.sqrt(np.maximum(0.0, 2 * DECEL * (Q_MAX - q)))))
    lo = np.maximum(-DQ_MAX, np.minimum(0.0, V_OFFSET - np.sqrt(np.maximum(0.0, 2 * DECEL * (q - Q_MIN)))))
    return lo + TOLERANCE, up - TOLERANCE
