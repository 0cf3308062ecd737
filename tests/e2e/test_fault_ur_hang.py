"""No hang: the UR controller vanishes right before a move (the emulator process is frozen
with SIGSTOP: no FIN, no RST, like a pulled cable) while ur_rtde's moveJ waits for its acknowledgement. The
station must raise ConnectionLost within the RTDE stall timeout (URL ``stall_ms``), and Ctrl-C must take
effect within ~1 s. Real ur_rtde against the emulator in a child process."""

from __future__ import annotations

import _thread
import gc
import signal
import threading
import time

import pytest
from faultrig import realtime_ur

from station.robot import ConnectionLost, open_robot


class _FreezeBefore:
    """The robot's control interface, unchanged, except that the controller freezes just before ``name``
    goes on the wire (the fault's timing; the call itself is ur_rtde's)."""

    def __init__(self, inner, proc, name: str) -> None:
        self._inner, self._proc, self._name = inner, proc, name

    def __getattr__(self, attr):
        value = getattr(self._inner, attr)
        if attr != self._name:
            return value

        def frozen(*args):
            self._proc.send_signal(signal.SIGSTOP)
            return value(*args)
        return frozen


@pytest.fixture
def frozen_before_movej(tmp_path, emulators):
    emu = realtime_ur(tmp_path, emulators, seed=5)
    robot = open_robot(emu.url + "&stall_ms=300")
    robot.enable()
    robot._c = _FreezeBefore(robot._c, emu.proc, "moveJ")
    yield robot, emu
    emu.proc.send_signal(signal.SIGCONT)
    robot.close()


def test_link_lost_before_movej_detected_within_stall_timeout(frozen_before_movej):
    robot, emu = frozen_before_movej
    q = robot.joint_positions().q
    t0 = time.monotonic()
    with pytest.raises(ConnectionLost) as e:
        robot.move_joints(q + 0.05)
    took = time.monotonic() - t0
    print(f"\nUR link lost before moveJ: ConnectionLost after {took * 1e3:.0f} ms (stall_ms=300)")
    assert "did not acknowledge moveJ within 300 ms" in str(e.value) and "\n" not in str(e.value)
    assert took < 0.3 + 0.5
    t1 = time.monotonic()
    with pytest.raises(ConnectionLost):  # later calls fail fast, no second hang
        robot.move_joints(q + 0.05)
    assert time.monotonic() - t1 < 0.6


def test_ctrl_c_during_hanging_movej_takes_effect_within_a_second(frozen_before_movej):
    robot, emu = frozen_before_movej
    robot.stale_timeout = 30.0  # without the stall bound: only Ctrl-C can end the wait
    q = robot.joint_positions().q
    pressed: list[float] = []

    def ctrl_c() -> None:  # the moment of the Ctrl-C itself: a loaded host wakes the timer thread late
        pressed.append(time.monotonic())
        _thread.interrupt_main()
    timer = threading.Timer(0.3, ctrl_c)
    # no garbage collection meanwhile: a gc callback that hypothesis installs in this test process (an earlier
    # test file on the same worker) swallows a KeyboardInterrupt raised inside it ("Exception ignored in
    # gc_callback"); the station itself registers none
    gc.disable()
    t0 = time.monotonic()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            robot.move_joints(q + 0.05)
    finally:
        gc.enable()
    took = time.monotonic() - pressed[0]
    assert pressed[0] - t0 >= 0.3
    print(f"\nCtrl-C during a hanging moveJ: acted on after {took * 1e3:.0f} ms")
    assert took < 1.0
    t1 = time.monotonic()
    with pytest.raises(ConnectionLost):  # the teardown's stop() is refused at once, it does not hang
        robot.stop()
    assert time.monotonic() - t1 < 0.6
