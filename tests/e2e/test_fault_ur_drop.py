"""UR link drop and the teardown (fault matrix: UR x disconnect): the controller closes every socket and
refuses connections for a while (``emulator drop S`` on the emulator's dashboard). The teardown cannot stop the
ur_rtde control program over a link that is gone; close() keeps trying the dashboard ``stop`` for
``URRobot.TEARDOWN_S`` (a short outage), and says loudly when the controller stayed unreachable. The next
connection uploads a fresh control script and moves. Truth from the emulator's dashboard (program state,
encoders); real ur_rtde against the emulator in a child process."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from faultrig import realtime_ur, ur_truth

from station.robot import ConnectionLost, open_robot


@pytest.fixture
def ur(tmp_path, emulators):
    return realtime_ur(tmp_path, emulators, seed=6)


def _drop_and_fail_a_move(emu, robot, seconds: float) -> None:
    q = robot.joint_positions().q
    robot.move_joints(q + np.array([0.05, 0, 0, 0, 0, 0]))  # the control script runs
    assert ur_truth(emu)[0].startswith("PLAYING")
    emu.dashboard(f"emulator drop {seconds}")
    with pytest.raises(ConnectionLost):
        robot.move_joints(q)
        robot.joint_positions()


def test_teardown_stops_the_program_once_a_short_drop_is_over(ur):
    robot = open_robot(ur.url)
    _drop_and_fail_a_move(ur, robot, 0.8)
    t0 = time.monotonic()
    robot.close()
    took = time.monotonic() - t0
    state, _, q0 = ur_truth(ur)
    time.sleep(0.1)
    assert not state.startswith("PLAYING"), state  # stopped by the teardown, not left running
    assert ur_truth(ur)[2] == q0  # the arm is still
    assert took < robot.TEARDOWN_S + 3.0  # bounded: no hang (closing the broken ur_rtde interfaces takes ~1 s)


def test_teardown_says_loudly_when_the_controller_stays_unreachable(ur, caplog):
    robot = open_robot(ur.url)
    robot.TEARDOWN_S = 0.5
    _drop_and_fail_a_move(ur, robot, 5.0)  # outlasts the teardown's tries even when closing is slow (load)
    with caplog.at_level(logging.WARNING, logger="station.drivers.ur"):
        robot.close()
    loud = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING
            and "could not stop the robot program" in r.getMessage()]
    assert len(loud) == 1 and "\n" not in loud[0] and "teach pendant" in loud[0], caplog.text
    state, _, _ = ur_truth(ur, timeout=8.0)  # once the controller is back: the lost client's program still runs,
    # unless the failed move's own watchdog reached the controller before the link went (a race a loaded host
    # decides; the controller then stopped the program itself, as it does a dead station's, and says so)
    if not state.startswith("PLAYING"):
        assert state.startswith("STOPPED"), state
        assert "RTDE watchdog expired" in ur.dashboard("emulator log"), state
    # the next connection replaces it with a fresh control script and moves the arm
    with open_robot(ur.url) as robot2:
        q = robot2.joint_positions().q
        robot2.move_joints(q + np.array([0.05, 0, 0, 0, 0, 0]))
        np.testing.assert_allclose(robot2.joint_positions().q, q + np.array([0.05, 0, 0, 0, 0, 0]), atol=1e-3)
    assert not ur_truth(ur)[0].startswith("PLAYING")  # and its close() stops it
