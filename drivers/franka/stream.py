"""The driver's own 1 kHz loop: one ``Move`` of libfranka's joint-position interface with an internal controller
(joint or Cartesian impedance), streamed from a thread with ``readOnce``/``writeOnce`` (pylibfranka's external
control loop) until finished.

It serves what the robot-side generator cannot: a motion under Cartesian impedance (libfranka's
``AsyncPositionControlHandler`` always runs joint impedance), and moves with ``motion=stream``. The loop follows
robot time (the sum of the periods libfranka reports), so a cycle this process misses is skipped, not
replayed; the robot extrapolates a missed cycle and aborts the motion with
``communication_constraints_violation`` after too many in a row (Franka: "Robot and interface
specifications", communication constraints), which ends this loop with the error for the driver to handle.

Units: rad, s."""

from __future__ import annotations

import contextlib
import gc
import os
import sys
import threading
import time

import numpy as np
from station.drivers.franka.trajectory import Quintic, plan

RT_PRIORITY = 80  # SCHED_FIFO priority of the loop (libfranka's control loops take the highest)

@contextlib.contextmanager
def keep_scheduling():
    """The calling thread's scheduling as it was before the block: libfranka makes the thread that opens a
    ``Robot`` run SCHED_FIFO at priority 99 where the system allows it (measured: the station's main thread
    after ``pf.Robot(...)``, with ``RealtimeConfig.kIgnore`` too). That priority is for a control loop that
    blocks every millisecond; the station's main thread plans and solves for seconds, and at 99 it shut the
    rest of the host out of a core -- in CI a process forked from it burned two cores at 99 and a simulator
    could not start in 60 s. The driver's own 1 kHz loop raises its own thread (``StreamLoop._realtime``)."""
    policy = param = None
    with contextlib.suppress(OSError, AttributeError):
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        yield
    finally:
        if policy is not None:
            with contextlib.suppress(OSError):
                if (os.sched_getscheduler(0), os.sched_getparam(0)) != (policy, param):
                    os.sched_setscheduler(0, policy, param)


SWITCH_INTERVAL = 2e-4  # s: how long the loop may wait for the GIL while another thread runs Python (a fifth of
# a cycle; Python's default is 5 ms, five lost cycles each time)

_lock = threading.Lock()
_holders = 0  # loops running now
_saved: tuple[bool, float] = (True, 0.005)  # the process's settings before the first loop


@contextlib.contextmanager
def gil_for_the_loop():
    """The process gives the 1 kHz loop the GIL in time while a loop runs; the loop needs it every cycle, and
    the robot aborts the motion with ``communication_constraints_violation`` after 20 lost cycles in a row.

    - No automatic cyclic garbage collection: a full collection holds the GIL for the whole scan of the heap,
      ~0.4 s for 2 million objects measured here, and an integrator's process (or a test worker after a
      thousand tests) is that big. That is the seating press aborted in CI, reproduced with such a collection
      in the same process. Reference counting still frees what the loop and the driver allocate; cycles wait
      for the end of the motion.
    - A short switch interval (``SWITCH_INTERVAL``): a thread running Python keeps the GIL for up to 5 ms by
      default before a waiting thread gets it.

    The caller's settings come back when the last loop ends."""
    global _holders, _saved
    with _lock:
        if _holders == 0:
            _saved = (gc.isenabled(), sys.getswitchinterval())
            gc.disable()
            sys.setswitchinterval(SWITCH_INTERVAL)
        _holders += 1
    try:
        yield
    finally:
        with _lock:
            _holders -= 1
            if _holders == 0:
                enabled, interval = _saved
                sys.setswitchinterval(interval)
                if enabled:
                    gc.enable()


class StreamLoop:
    """One streamed motion. ``move_to`` gives it a new target (a quintic from the commanded state);
    between targets it holds the last one. ``finish()`` ends the motion cleanly; ``error`` holds the exception
    that ended it otherwise."""

    def __init__(self, robot, pf, controller_mode, accel: float, jerk: float) -> None:
        self._robot, self._pf = robot, pf
        self.mode = controller_mode
        self.accel, self.jerk = accel, jerk
        self._lock = threading.Lock()
        self._path: Quintic | None = None
        self._t = 0.0  # robot time since the path started
        self._target: np.ndarray | None = None
        self._finish = threading.Event()
        self.started = threading.Event()
        self.done = threading.Event()
        self.error: BaseException | None = None
        self.state = None  # the latest robot state of the loop
        self.state_time = 0.0  # monotonic time it arrived
        self.cycles = 0
        self.scheduling = ""
        self.commanded = None  # the last (p, v, a) sent
        self._thread = threading.Thread(target=self._run, name="franka-1khz", daemon=True)

    def start(self, timeout: float = 5.0) -> StreamLoop:
        self._thread.start()
        if not self.started.wait(timeout) and self.error is None:
            self.error = TimeoutError("the motion did not start")
        if self.error is not None:
            self.done.wait(1.0)
            raise self.error
        return self

    # ---- called from the driver's thread ----------------------------------------------------------------------
    def move_to(self, q, speed) -> Quintic:
        with self._lock:
            p, v, a = self.commanded
            path = plan(p, v, a, np.asarray(q, float), speed, self.accel, self.jerk)
            self._path, self._t, self._target = path, 0.0, np.asarray(q, float).copy()
        return path

    def path_done(self) -> bool:
        with self._lock:
            return self._path is None or self._t >= self._path.T

    def finish(self, timeout: float = 3.0) -> None:
        self._finish.set()
        self.done.wait(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive() and not self.done.is_set()

    # ---- the loop -----------------------------------------------------------------------------------------------
    def _realtime(self) -> str:
        """Run this thread ahead of ordinary work where the system allows it, as libfranka does for its own control
        loops (``setCurrentThreadToHighestSchedulerPriority``): SCHED_FIFO, else a nice of -10, else as it is.
        The loop blocks on every robot state (1 ms), so it cannot starve the host."""
        tid = threading.get_native_id()
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
            return "SCHED_FIFO"
        except (OSError, AttributeError):
            pass
        try:
            os.setpriority(os.PRIO_PROCESS, tid, -10)
            return "nice -10"
        except (OSError, AttributeError):
            return "normal"

    def _run(self) -> None:
        with gil_for_the_loop():
            self._stream()

    def _stream(self) -> None:
        pf = self._pf
        ctrl = None
        self.scheduling = self._realtime()
        try:
            ctrl = self._robot.start_joint_position_control(self.mode)
            state, _ = ctrl.readOnce()
            q0 = np.asarray(state.q_d, float)
            self.commanded = (q0, np.zeros(7), np.zeros(7))
            self.state, self.state_time = state, time.monotonic()
            self.started.set()
            while True:
                state, period = ctrl.readOnce()
                self.state, self.state_time = state, time.monotonic()
                self.cycles += 1
                dt = period.to_sec()
                with self._lock:
                    if self._path is not None:
                        self._t += dt
                        p, v, a = self._path.sample(self._t)
                    else:
                        p, v, a = self.commanded[0], np.zeros(7), np.zeros(7)
                    self.commanded = (p, v, a)
                cmd = pf.JointPositions(p.tolist())
                if self._finish.is_set() and self.path_done():
                    cmd.motion_finished = True
                    ctrl.writeOnce(cmd)
                    break
                ctrl.writeOnce(cmd)
        except BaseException as e:  # a reflex (ControlException), a lost link (NetworkException), anything
            # kept without its traceback: the frames would keep the active control (libfranka's control lock)
            # alive, and no new motion could start
            self.error = e.with_traceback(None)
        finally:
            del ctrl  # releases libfranka's control lock
            self._robot = None  # and the loop keeps no connection alive
            self.started.set()
            self.done.set()
