"""``station.tui.hold``: hold-to-run learns the terminal's key cadence from the key events (repeat delay, repeat
interval) and infers the release from a gap of 2.5 intervals, within [50 ms, 100 ms] (docs/jog.md
"Hold-to-run"); the arm of the emulated world moves while the key is held and stands after the inferred release."""

from __future__ import annotations

import numpy as np
import pytest
from station.mocks.world import World

from station.tui.controller import JogController
from station.tui.hold import HOLD_FIRST_S, HOLD_GAP_MIN_S, HOLD_RELEASE_S, HoldToRun
from station.tui.session import session_header, technician_session

START = [0.0, -0.5, 0.5, 0.0, 0.6, 0.0]


@pytest.fixture
def ctl(tmp_path, robot_rig):
    world = World.default(model="arm6", seed=5, start=START, time_mode="instant")
    _, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
    header = session_header(identity=robot.identity(), model_name="arm6", serial="SN-H", identify="offsets",
                            reference="unknown", url="x")
    c = JogController(robot, technician_session(robot, header, folder=tmp_path / "s"), identify="offsets")
    yield world, c
    c.close()


def test_cadence_is_learned_from_the_key_events(ctl):
    world, c = ctl
    h = c.holding
    assert isinstance(h, HoldToRun) and h.release_gap() == HOLD_RELEASE_S and h.first_window() == HOLD_FIRST_S
    q0 = world.encoder_q().copy()
    t = 1000.0
    assert h.hold(1, +1, now=t)  # the press
    t += 0.4  # the terminal's repeat delay
    h.hold(1, +1, now=t)
    for _ in range(20):  # repeats every 33 ms
        t += 0.033
        h.hold(1, +1, now=t)
        h.hold_tick(now=t)
    assert h.release_gap() == pytest.approx(2.5 * 0.033)
    assert not h.hold_check(now=t + 0.05)  # inside the gap: still held
    assert h.hold_check(now=t + 0.09) and h.hold_state is None  # past 2.5 intervals: released, stopped
    assert h.repeat_delay == pytest.approx(0.4)
    assert h.first_window() == pytest.approx(0.4 + 0.1)  # the delay plus a quarter
    assert np.abs(world.encoder_q() - q0)[1] > 1e-4  # the held joint moved


def test_the_gap_stays_within_its_bounds(ctl):
    _, c = ctl
    h = c.holding
    h.repeat_intervals.extend([0.005] * 16)  # a terminal repeating at 200 Hz
    assert h.release_gap() == HOLD_GAP_MIN_S
    h.repeat_intervals.extend([0.2] * 16)  # or at 5 Hz: never longer than the watchdog period
    assert h.release_gap() == HOLD_RELEASE_S
    h.release_events = True  # a terminal that reports releases: the gap is only the backup
    assert h.release_gap() == HOLD_RELEASE_S
