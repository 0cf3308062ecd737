"""``station.drivers.franka.stream``: the driver's 1 kHz loop against a stand-in for pylibfranka's external
control loop (``readOnce`` hands out a state and the period, ``writeOnce`` takes a ``JointPositions``), which
records what the loop commands. What is checked is the loop's own logic: it follows robot time, keeps the
quintic's speed and acceleration, finishes with ``motion_finished`` only once the path is done, and keeps the
error that ended it. The same loop against franka-sim: tests/drivers/franka/test_franka_driver.py."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
from station.drivers.franka.stream import StreamLoop

DT = 0.001


class _Positions:
    def __init__(self, q) -> None:
        self.q = list(q)
        self.motion_finished = False


class _Control:
    """One motion: the robot's state is where the last command put it (a perfect tracker); ``fail_after``
    cycles make ``readOnce`` raise as libfranka does on a reflex."""

    def __init__(self, q0, fail_after: int | None = None) -> None:
        self.q = np.asarray(q0, float)
        self.sent: list[_Positions] = []
        self.fail_after = fail_after

    def readOnce(self):  # noqa: N802 (pylibfranka's name)
        if self.fail_after is not None and len(self.sent) >= self.fail_after:
            raise RuntimeError("Motion aborted by reflex! [\"joint_velocity_violation\"]")
        time.sleep(0.0002)
        state = SimpleNamespace(q=self.q.tolist(), q_d=self.q.tolist(), dq=[0.0] * 7)
        return state, SimpleNamespace(to_sec=lambda: DT)

    def writeOnce(self, cmd):  # noqa: N802
        self.sent.append(cmd)
        self.q = np.asarray(cmd.q, float)


class _Robot:
    def __init__(self, control) -> None:
        self.control = control

    def start_joint_position_control(self, mode):
        return self.control


PF = SimpleNamespace(JointPositions=_Positions)
Q0 = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "the loop did not get there"
        time.sleep(0.005)


def test_the_loop_streams_a_jerk_limited_path_and_finishes_cleanly():
    ctrl = _Control(Q0)
    loop = StreamLoop(_Robot(ctrl), PF, "joint", accel=2.0, jerk=500.0).start()
    assert loop.alive and loop.cycles >= 0
    target = Q0 + np.array([0.0, 0.0, 0.0, 0.1, 0.0, 0.0, -0.05])
    path = loop.move_to(target, 0.5)
    _wait(loop.path_done)
    loop.finish()
    assert loop.done.is_set() and loop.error is None and not loop.alive
    q = np.array([c.q for c in ctrl.sent])
    assert np.allclose(q[-1], target, atol=1e-12) and ctrl.sent[-1].motion_finished
    assert not any(c.motion_finished for c in ctrl.sent[:-1])
    v = np.diff(q, axis=0) / DT
    assert np.max(np.abs(v)) <= 0.5 * 1.001  # the speed asked for, in robot time
    assert np.max(np.abs(np.diff(v, axis=0))) / DT <= 2.0 * 1.01  # the acceleration cap
    # the path took its planned duration in robot time (cycles), whatever the wall clock did
    moving = np.flatnonzero(np.any(np.abs(np.diff(q, axis=0)) > 0, axis=1))
    assert (moving[-1] - moving[0] + 1) * DT == pytest.approx(path.T, abs=3 * DT)


def test_a_new_target_starts_from_the_commanded_state_and_a_reflex_ends_the_loop_with_its_error():
    ctrl = _Control(Q0)
    loop = StreamLoop(_Robot(ctrl), PF, "cartesian", accel=2.0, jerk=500.0).start()
    loop.move_to(Q0 + 0.2, 1.0)
    _wait(lambda: len(ctrl.sent) > 50)
    loop.move_to(Q0, 1.0)  # turned round mid-path: from where it is commanded, no jump in position or speed
    _wait(loop.path_done)
    q = np.array([c.q for c in ctrl.sent])
    assert np.max(np.abs(np.diff(q, axis=0))) / DT <= 1.0 * 1.001
    assert np.max(np.abs(np.diff(q, n=2, axis=0))) / DT ** 2 <= 2.0 * 1.01
    ctrl.fail_after = len(ctrl.sent)
    _wait(loop.done.is_set)
    assert isinstance(loop.error, RuntimeError) and "reflex" in str(loop.error) and not loop.alive
    assert loop.error.__traceback__ is None  # kept without its frames (they would hold libfranka's control lock)


def test_while_a_loop_runs_no_collection_and_no_long_wait_keeps_the_gil_from_it():
    """A full cyclic collection holds the GIL for the whole heap (~0.4 s for 2 million objects), and Python lets
    a running thread keep the GIL 5 ms by default: either loses the robot 5-400 cycles. While any loop runs,
    the process collects nothing automatically and switches threads within a fifth of a cycle; the settings
    the process had come back when the last loop ends (two loops overlapping: a compliant hold and a move)."""
    import gc
    import sys
    import threading

    gc.enable()
    before = sys.getswitchinterval()
    started = []

    def seen(phase, info):
        if phase == "start":
            started.append(info["generation"])

    first = StreamLoop(_Robot(_Control(Q0)), PF, "joint", accel=2.0, jerk=500.0).start()
    second = StreamLoop(_Robot(_Control(Q0)), PF, "joint", accel=2.0, jerk=500.0).start()
    gc.callbacks.append(seen)
    try:
        stop = threading.Event()

        def garbage():  # another thread of the process makes cycles, as an integrator's program would
            while not stop.is_set():
                for _ in range(1000):
                    a: list = []
                    a.append(a)
                time.sleep(0.001)

        maker = threading.Thread(target=garbage)
        maker.start()
        time.sleep(0.3)
        assert not gc.isenabled() and sys.getswitchinterval() <= 0.2 * DT
        first.finish()
        time.sleep(0.1)
        assert not gc.isenabled()  # the second loop still runs
        stop.set()
        maker.join()
        assert started == []  # no collection of any generation while a loop ran
        second.finish()
    finally:
        gc.callbacks.remove(seen)
    assert first.error is None and second.error is None
    assert gc.isenabled() and sys.getswitchinterval() == before
