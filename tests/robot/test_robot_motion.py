"""``station.robot.motion``: the limit check, jog targets and the manual tool-speed cap every driver applies."""

from __future__ import annotations

import numpy as np
import pytest

from station.kinematics import load_model
from station.robot.errors import LimitError
from station.robot.motion import MANUAL_TOOL_SPEED_CAP, check_joint_limits, jog_target, joint_speed_for_tool_cap

HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])


@pytest.fixture(scope="module")
def ur5e():
    return load_model("ur5e")


def test_limits_are_checked_in_user_units(ur5e):
    assert check_joint_limits(ur5e, HOME) is not None
    q = HOME.copy()
    q[2] = ur5e.upper[2] + 0.01
    with pytest.raises(LimitError, match=r"^target: joint 3 \(\w+\) = [\d.]+ deg is outside its limits") as e:
        check_joint_limits(ur5e, q)
    assert f"{np.degrees(q[2]):.3f} deg" in str(e.value) and "nothing was sent" in str(e.value)
    with pytest.raises(LimitError, match="expected 6 joint values"):
        check_joint_limits(ur5e, HOME[:5])
    with pytest.raises(LimitError, match="must be finite"):
        check_joint_limits(ur5e, np.r_[HOME[:5], np.nan])


def test_joint_and_cartesian_jog_steps(ur5e):
    t = jog_target(ur5e, HOME, "joint", 1, 0.01)
    assert np.allclose(t - HOME, [0, 0.01, 0, 0, 0, 0])
    # 2 mm along base y: forward kinematics of the answer moved the tool by exactly that, orientation kept
    t = jog_target(ur5e, HOME, "cartesian", 1, 0.002)
    T0, T1 = ur5e.fk(HOME), ur5e.fk(t)
    assert np.allclose(T1[:3, 3] - T0[:3, 3], [0, 0.002, 0], atol=1e-6)
    assert np.allclose(T1[:3, :3], T0[:3, :3], atol=1e-5)
    # 1 deg about base z through the TCP: the tool point stays, the frame turns by 1 deg
    t = jog_target(ur5e, HOME, "cartesian", 5, np.radians(1))
    T1 = ur5e.fk(t)
    assert np.allclose(T1[:3, 3], T0[:3, 3], atol=1e-6)
    R = T1[:3, :3] @ T0[:3, :3].T
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(1.0, abs=1e-4)
    for args, needle in (((9, 0.1), "does not exist"), ((7, 0.1), "must be 0..5")):
        with pytest.raises(LimitError, match=needle):
            jog_target(ur5e, HOME, "joint" if args[0] == 9 else "cartesian", *args)
    with pytest.raises(LimitError, match="not reachable"):
        jog_target(ur5e, HOME, "cartesian", 0, 3.0)


def test_tool_speed_cap_holds_along_the_path(ur5e):
    q1 = HOME + np.array([0.6, 0.3, -0.3, 0.2, 0.1, 0.5])
    speed = joint_speed_for_tool_cap(ur5e, HOME, q1, requested=None)
    assert 0 < speed <= ur5e.max_velocity.min()
    # tool speed by finite differences of forward kinematics along the straight joint path at that lead speed
    dq = q1 - HOME
    lead = np.abs(dq).max()
    s = np.linspace(0, 1, 201)
    p = ur5e.fk(HOME + s[:, None] * dq)[:, :3, 3]
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / (np.diff(s)[:, None][:, 0] * lead / speed)
    assert v.max() <= MANUAL_TOOL_SPEED_CAP * 1.02  # the cap (8 samples along the path; 2 % between them)
    assert v.max() >= 0.8 * MANUAL_TOOL_SPEED_CAP  # and not needlessly slow
    assert joint_speed_for_tool_cap(ur5e, HOME, q1, requested=1e-3) == 1e-3
