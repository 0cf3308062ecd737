"""``franka://HOST[?model=fr3&serial=SN&motion=async&speed=0.5&stiffness=600&contact_force=2]``: a Franka
Research 3 arm over the FCI (libfranka server version 10) through Franka's own Python bindings, pylibfranka
(options: ``FrankaRobot.options``; docs/hardware-franka.md).

Units: joints rad, joint speed rad/s, forces N, stiffness N/m and N m/rad.

- Joint moves: the robot's own asynchronous position generator (``AsyncPositionControlHandler``: the driver
  sends a target, Control generates the motion at 1 kHz, nothing here runs at 1 kHz), or with ``motion=stream``
  the driver's jerk-limited quintic streamed from its own 1 kHz loop (``drivers.franka.stream``). Targets are
  checked against the joint limits and speeds against Franka's limits before anything is sent.
- Compliance: ``set_compliant(True)`` runs a Cartesian-impedance motion (``SetCartesianImpedance`` stiffness
  ``stiffness``/``rot_stiffness``) from the driver's 1 kHz loop; moves while compliant are moves of that
  motion, so a ball driven a few millimetres past a socket seats under the arm's own control. Compliance taken
  up right after a stiff move presses on along it with ``press_force`` (``drivers.franka.press``): the cone,
  not where the stiff move stopped, decides where the ball rests.
- Contact: ``touch()`` is the estimated external force (``O_F_ext_hat_K``) against the force at rest when
  compliance began, above ``contact_force``.
- Faults: a motion the robot aborts for a communication-constraint violation is recovered
  (``automatic_error_recovery``) and retried up to ``retries`` times; other reflexes stop the robot and raise.
- Identity: the model the robot serves is checked against the station's model (``drivers.franka.identity``).
- Calibration: the robot keeps its kinematics itself; ``export_calibration`` writes a calibrated URDF and
  station model file (nothing is written to the robot)."""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np
from station.drivers.franka import identity as ident
from station.drivers.franka import limits, press
from station.drivers.franka.stream import StreamLoop, keep_scheduling

from station.kinematics import Model
from station.robot.base import CHAIN_OPTIONS, RobotBase
from station.robot.errors import BusError, ConfigError, ConnectionLost, DeviceFault, LimitError, SafetyStop
from station.robot.protocol import Identity, JointSnapshot, JointState, RobotStatus
from station.robot.registry import bus_library
from station.robot.url import Option, Options, RobotURL, either, integer, number, text

with bus_library("pylibfranka"):
    import pylibfranka as pf

log = logging.getLogger("station.drivers.franka")

GOAL_TOL = 2e-4  # rad: the generator has arrived when its command is this close to the target ...
REST_DQ = 5e-3  # rad/s: ... and the move is over when the arm is slower than this ...
REST_TOOL = 1e-3  # m/s: a compliant arm rests when its end effector is slower than this
FOLLOW_TOL = 5e-3  # rad: ... within this of the target (an impedance controller leaves a small steady error)
SETTLE_S = 5.0  # s a move may take beyond its plan to settle before it is a fault (a loaded host slows the sim)
COMM_VIOLATION = "communication_constraints_violation"
COLLISION = ("cartesian_reflex", "joint_reflex", "self_collision_avoidance_violation")
NETWORK_WORDS = ("UDP receive", "TCP receive", "server closed connection", "TCP connection got interrupted")
# collision thresholds set at connect (N m per joint, N / N m per Cartesian axis; lower = contact, upper =
# reflex): Franka's examples' defaults (libfranka examples/examples_common.cpp setDefaultBehavior)
TORQUE_THRESHOLDS = [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0]
FORCE_THRESHOLDS = [20.0, 20.0, 20.0, 25.0, 25.0, 25.0]
JOINT_STIFFNESS = [3000.0, 3000.0, 3000.0, 2500.0, 2500.0, 2000.0, 2000.0]  # N m/rad, the same examples



def _frameless(method):
    """An error leaves the driver without its frames (and without the exception it was translated from): a
    caller that keeps it -- the engine's outcome, a test, an integrator's log -- would otherwise keep the
    frames' ``pf.Robot`` and asynchronous handler, and with them the FCI connection, open after ``close()``
    (the FCI serves one client: the next connection waits for ever). The message is the one line it was."""
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except Exception as e:
            e.__context__ = e.__cause__ = None
            raise e.with_traceback(None) from None

    return call

class FrankaRobot(RobotBase):
    """Fulfils ``station.robot.Robot`` for Franka Research 3 arms; capabilities: contact sensing (estimated
    external force), compliance (Cartesian impedance), calibration export, protective-stop (reflex) recovery,
    reconnect."""

    vendor = "Franka Robotics"
    options = Options(
        Option("model", text(), "fr3", "kinematic model (`fr3`, a model file or a URDF with the flange as tip)",
               default_doc="`fr3`"),
        Option("serial", text(), None, "the arm's serial number (the FCI reports none: Desk shows it); "
               "without it the operator's `--serial` is used"),
        Option("motion", either("async", "stream"), "async", "joint moves: `async` = the robot's own "
               "asynchronous position generator (libfranka >= 0.18, system image >= 5.9), `stream` = the "
               "driver's quintic from its 1 kHz loop"),
        Option("speed", number(0, unit="rad/s", open_low=True), None, "default speed of the joint that moves "
               "most in `move_joints`, at most the slowest joint's maximum", default_doc="`0.5`"),
        Option("accel", number(0, 10, unit="rad/s^2", open_low=True), 2.0, "joint acceleration of streamed "
               "moves (Franka: 10 rad/s^2 at most)"),
        Option("stiffness", number(10, 3000, unit="N/m"), 600.0, "translational stiffness of the Cartesian "
               "impedance while compliant"),
        Option("rot_stiffness", number(1, 300, unit="N m/rad"), 30.0, "rotational stiffness while compliant"),
        Option("contact_force", number(0.3, 50, unit="N"), 2.0, "`touch()` is true when the estimated external "
               "force differs this much from the force at rest when compliance began (after a move: before it)"),
        Option("press_force", number(0, 20, unit="N"), 5.0, "compliance taken up right after a stiff move "
               "presses on along that move's tool direction with this force (the impedance target "
               "`press_force/stiffness` beyond, at most 6 mm of travel before contact), so the socket's cone "
               "centres the ball; 0: hold where the move stopped"),
        Option("retries", integer(0, 10), 3, "motions aborted by a communication-constraint violation are "
               "recovered and retried this often before it is a fault"),
        Option("realtime", either("ignore", "enforce"), "ignore", "libfranka's real-time scheduling check "
               "(`enforce` needs a PREEMPT_RT kernel and rights; the asynchronous generator does not need it)"),
        Option("export", text(), None, "folder for calibration exports", default_doc="`./franka-calibration-SERIAL/`"),
        *CHAIN_OPTIONS,
    )

    def __init__(self, host: str, model: Model, *, serial: str | None = None, motion: str = "async",
                 speed: float = 0.5, accel: float = 2.0, stiffness: float = 600.0, rot_stiffness: float = 30.0,
                 contact_force: float = 2.0, press_force: float = 5.0, retries: int = 3, realtime: str = "ignore",
                 export_dir: str | None = None, url: str = "", connect: bool = True) -> None:
        self.host = host
        self.model = model
        self.serial = serial or ""
        self.motion = motion
        self.speed, self.accel = speed, accel
        self.stiffness, self.rot_stiffness = stiffness, rot_stiffness
        self.contact_force, self.press_force = contact_force, press_force
        # read by the seating step: a robot that presses is brought stiff only this close to the seated pose
        self.seat_standoff = press.STANDOFF if press_force > 0 else 0.0
        self._last_move: tuple | None = None  # (q from, q to, external force at rest before) of the last stiff move
        self.last_press: str | None = None  # how the last seating press ended (seated, no contact, not settled)
        self._moved_at = -math.inf  # monotonic time the last move ended as asked
        self.retries = retries
        self.realtime = realtime
        self.export_dir = export_dir
        self.url = url or f"franka://{host}?model={model.name}"
        self.last_export: list[Path] = []
        self.recoveries: list[str] = []  # every automatic recovery, for logs and tests
        self._robot = None
        self._served = None  # libfranka's model built from the URDF the robot serves
        self._served_diff = math.nan
        self._handler = None  # the running asynchronous position motion
        self._handler_vmax: tuple | None = None
        self._loop: StreamLoop | None = None  # the running streamed motion
        self._tare: np.ndarray | None = None  # external force at rest when compliance began
        self._compliant_target: np.ndarray | None = None  # the last target of the compliant hold, and its speed
        self._compliant_speed = speed
        self._revivals = 0  # holds taken up again in this compliant phase
        self._interrupt = threading.Event()
        self._lock = threading.RLock()
        if connect:
            self.connect()

    # ---- construction -------------------------------------------------------------------------------------
    @classmethod
    def from_url(cls, url: RobotURL, **overrides) -> FrankaRobot:
        o = cls.options.parse(url)
        if not url.host:
            raise ConfigError(f"robot URL {url.raw!r}: franka:// needs the robot's address (the FCI address set "
                              "in Desk), e.g. franka://172.16.0.2")
        if url.port is not None:
            raise ConfigError(f"robot URL {url.raw!r}: franka:// takes no port (the FCI listens on 1337)")
        model = cls.load_url_model(url, o["model"], o["tip_link"], o["base_link"])
        if model.n_joints != 7 or not all(j.revolute for j in model.joints):
            raise ConfigError(f"robot URL {url.raw!r}: model {model.name} has {model.n_joints} joints; a Franka arm "
                              "has 7 revolute joints")
        vmax = float(min(model.max_velocity.min(), limits.DQ_MAX.min()))
        if o["speed"] is not None and o["speed"] > vmax:
            raise ConfigError(f"robot URL {url.raw!r}: speed={o['speed']:g} must be in (0, {vmax:g}] rad/s")
        args = dict(serial=o["serial"], motion=o["motion"], speed=o["speed"] or min(0.5, vmax), accel=o["accel"],
                    stiffness=o["stiffness"], rot_stiffness=o["rot_stiffness"], contact_force=o["contact_force"],
                    press_force=o["press_force"], retries=o["retries"], realtime=o["realtime"],
                    export_dir=o["export"], url=url.raw)
        args.update(overrides)
        return cls(url.host, model, **args)

    # ---- connection ---------------------------------------------------------------------------------------
    @property
    def where(self) -> str:
        return f"franka://{self.host}"

    @_frameless
    def connect(self) -> None:
        rt = pf.RealtimeConfig.kEnforce if self.realtime == "enforce" else pf.RealtimeConfig.kIgnore
        try:
            with keep_scheduling():
                self._robot = pf.Robot(self.host, rt)
        except Exception as e:  # NetworkException, IncompatibleVersionException, RealtimeException
            raise ConnectionLost(f"{self.where}: cannot connect to the FCI: {_one_line(e)} (robot on, brakes open "
                                 "and FCI activated in Desk? libfranka >= 0.18 needs system image >= 5.9)") from None
        try:
            state = self._robot.read_once()
            self._served = self._robot.load_model()
            # before anything moves: the station's model must be the robot's
            self._served_diff = ident.check_served_model(self.where, self.model, self._served, state)
            ident.check_reported_pose(self.where, self.model, state)
            self._robot.set_collision_behavior(TORQUE_THRESHOLDS, TORQUE_THRESHOLDS, FORCE_THRESHOLDS,
                                               FORCE_THRESHOLDS)
            self._robot.set_joint_impedance(JOINT_STIFFNESS)
        except Exception:
            self._drop()
            raise
        log.info("%s connected; served model matches %s to %.2g", self.where, self.model.name, self._served_diff)

    def _drop(self) -> None:
        """Let go of the connection: pylibfranka closes it when its ``Robot`` is destroyed (there is no close),
        so every reference goes, and a collection runs for any cycle still holding one (the FCI serves one
        client: a leaked ``Robot`` would keep the next one waiting)."""
        import gc

        self._handler = self._loop = None
        robot, self._robot = self._robot, None
        if robot is not None:
            del robot
            gc.collect()

    @_frameless
    def reconnect(self, timeout: float = 10.0) -> None:
        """Open the FCI connection again after ``ConnectionLost`` (retries until ``timeout`` s)."""
        self._check_open("reconnect")
        self._end_motions()
        self._drop()
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.connect()
                return
            except ConnectionLost as e:
                if time.monotonic() > deadline:
                    raise ConnectionLost(f"{self.where}: reconnect failed for {timeout:g} s: {e}") from None
                time.sleep(0.25)

    def _shutdown(self) -> None:
        """End any motion (the robot holds where it stands) and close the connection."""
        problems = []
        try:
            self._end_motions()
        except Exception as e:  # the link may be gone: still close
            problems.append(str(e))
        self._drop()
        if problems:
            log.warning("%s: closing: %s", self.where, "; ".join(problems))

    def _live(self, what: str):
        self._check_open(what)
        if self._robot is None:
            raise ConnectionLost(f"{what}: {self.where} is not connected (reconnect())")
        return self._robot

    # ---- state --------------------------------------------------------------------------------------------
    def _state(self, what: str = "read state"):
        """The newest robot state: the running 1 kHz loop's, else one read. A compliant hold the robot ended is
        taken up again first (``_revive_compliance``)."""
        loop = self._loop
        if self._compliant and (loop is None or not loop.alive):
            self._revive_compliance()
            loop = self._loop
        if loop is not None and loop.alive and loop.state is not None:
            return loop.state
        robot = self._live(what)
        try:
            return robot.read_once()
        except Exception as e:
            raise self._translate(e, what) from None

    @_frameless
    def joint_positions(self) -> JointSnapshot:
        s = self._state("joint_positions")
        q = np.asarray(s.q, float)
        return JointSnapshot(q=q, raw=tuple(float(x) for x in q), raw_unit="rad", t=time.time(),
                             t_device=float(s.time.to_sec()))

    def identity(self) -> Identity:
        self._live("identity")
        return Identity(vendor=self.vendor, model=self.model.name, serial=self.serial or f"franka@{self.host}",
                        firmware=f"FCI server 10 (libfranka {pf.__version__})",
                        devices=({"device": "arm", "served_model": "matches", "jacobian_max_diff": self._served_diff},),
                        url=self.url, serial_source="url" if self.serial else "derived")

    def _moving(self, s) -> bool:
        """Stiff: any joint faster than ``REST_DQ``. Compliant: the end effector faster than ``REST_TOOL`` (the
        arm's null space may creep under Cartesian impedance while the tool rests)."""
        dq = np.asarray(s.dq, float)
        if not self._compliant:
            return bool(np.any(np.abs(dq) > REST_DQ))
        J = self.model.jacobian_q(np.asarray(s.q, float)).reshape(6, 7)
        return bool(np.linalg.norm(J[:3] @ dq) > REST_TOOL or np.max(np.abs(dq)) > 0.05)

    @_frameless
    def status(self) -> RobotStatus:
        s = self._state("status")
        mode = s.robot_mode
        dq = np.asarray(s.dq, float)
        moving = self._moving(s)
        errors = str(s.current_errors) if s.current_errors else ""
        faults = tuple(x.strip().strip('"') for x in errors.strip("[]").split(",") if x.strip().strip('"'))
        if mode == pf.RobotMode.Reflex and not faults:
            faults = (f"reflex ({s.last_motion_errors})",)
        enabled = mode in (pf.RobotMode.Idle, pf.RobotMode.Move)
        joints = tuple(JointState(j.name, enabled, bool(abs(dq[i]) > REST_DQ)) for i, j in enumerate(self.model.joints))
        return RobotStatus(enabled=enabled, moving=moving, faults=faults, estop=False,
                           protective_stop=mode == pf.RobotMode.UserStopped,
                           compliant=self._compliant, joints=joints)

    @_frameless
    def touch(self) -> bool:
        """Contact by force: the estimated external force (``O_F_ext_hat_K``, robot on the environment) differs
        from the force at rest when compliance began by more than ``contact_force`` N."""
        s = self._state("touch")
        F = np.asarray(s.O_F_ext_hat_K, float)[:3]
        ref = self._tare if self._tare is not None else np.zeros(3)
        return bool(np.linalg.norm(F - ref) > self.contact_force)

    @_frameless
    def external_force(self) -> np.ndarray:
        """The estimated external wrench (N, N m; robot on the environment, base frame) as the robot reports it."""
        return np.asarray(self._state("external_force").O_F_ext_hat_K, float)

    # ---- motion -------------------------------------------------------------------------------------------
    @_frameless
    def move_joints(self, q, speed: float | None = None, wait: bool = True) -> None:
        target = self._checked_target(q, "move_joints")
        v = self._checked_speed(speed, "move_joints", upper=float(limits.DQ_MAX.min())) or self.speed
        self._interrupt.clear()
        self._note_move(target)
        for attempt in range(self.retries + 1):
            try:
                if self._compliant:
                    self._stream_move(target, v, wait, compliant=True)
                elif self.motion == "stream":
                    self._stream_move(target, v, wait, compliant=False)
                else:
                    self._async_move(target, v, wait)
                self._moved_at = time.monotonic()  # a stiff move that ended as asked: a press may follow it
                return
            except _Retry as r:
                if attempt >= self.retries:
                    self._await_standstill()
                    raise BusError(f"{self.where}: move aborted {attempt + 1} times by {r}; the robot holds where "
                                   "it stopped (a loaded station PC? motion=async needs no 1 kHz loop here)") from None
                self._recover(str(r))

    def _recover(self, why: str) -> None:
        """Clear a reflex the robot latched (``automatic_error_recovery``) and make ready to move again."""
        self._end_motions()
        robot = self._live("recover")
        try:
            robot.automatic_error_recovery()
        except Exception as e:
            raise self._translate(e, "automatic error recovery") from None
        self.recoveries.append(why)
        log.warning("%s: %s: recovered (automatic error recovery), retrying", self.where, why)
        if self._compliant:  # the force at rest stays the one from before any contact
            self._start_compliant_loop(tare=False)

    def _async_move(self, target: np.ndarray, speed: float, wait: bool) -> None:
        robot = self._live("move_joints")
        vmax = tuple(float(min(speed, v)) for v in limits.DQ_MAX)
        if self._handler is not None and self._handler_vmax != vmax:
            self._end_motions()
        if self._handler is None:
            cfg = pf.AsyncPositionControlHandler.Configuration(list(vmax), GOAL_TOL)
            try:
                with keep_scheduling():
                    res = pf.AsyncPositionControlHandler.configure(robot, cfg)
            except Exception as e:
                raise self._translate(e, "start of the position motion") from None
            if res.error_message is not None or res.handler is None:
                self._raise_motion_error(res.error_message or "no handler", "start of the position motion")
            self._handler, self._handler_vmax = res.handler, vmax
        h = self._handler
        res = h.set_joint_position_target(pf.AsyncPositionControlHandler.JointPositionTarget(target.tolist()))
        if not res.was_successful:
            self._end_motions()  # released now, not when the garbage collector gets to it
            self._raise_motion_error(res.error_message or "target refused", "move_joints")
        if not wait:
            return
        q0 = np.asarray(self._state("move_joints").q, float)
        deadline = time.monotonic() + float(np.max(np.abs(target - q0))) / speed + 3 * speed / 2.0 + SETTLE_S
        while True:
            if self._interrupt.is_set():  # stop() from another thread ended the motion
                raise SafetyStop(f"{self.where}: move_joints: stopped")
            fb = h.get_target_feedback()
            if self._interrupt.is_set():
                raise SafetyStop(f"{self.where}: move_joints: stopped")
            if fb.status == pf._pylibfranka.TargetStatus.kAborted:
                # released now: a traceback that keeps this frame alive would otherwise keep libfranka's control
                # slot taken, and the next motion after a recovery is refused
                self._end_motions()
                self._raise_motion_error(fb.error_message or "aborted", "move_joints")
            if fb.status == pf._pylibfranka.TargetStatus.kTargetReached and self._arrived(target):
                return
            if time.monotonic() > deadline:
                st = self._state("move_joints")
                why = (f"generator {fb.status.name}, max error {np.max(np.abs(np.asarray(st.q) - target)):.2g} rad, "
                       f"speed {np.max(np.abs(np.asarray(st.dq))):.2g} rad/s")
                self.stop()
                raise DeviceFault(f"{self.where}: move_joints: the arm did not reach its target in time ({why}); "
                                  "stopped")
            time.sleep(0.004)

    def _q(self) -> np.ndarray:
        return np.asarray(self._state("read joints").q, float)

    def _arrived(self, target: np.ndarray) -> bool:
        s = self._state("read joints")
        q, dq = np.asarray(s.q), np.asarray(s.dq)
        return bool(np.max(np.abs(q - target)) < FOLLOW_TOL and np.max(np.abs(dq)) < REST_DQ)

    def _stream_move(self, target: np.ndarray, speed: float, wait: bool, compliant: bool) -> None:
        if compliant:
            if self._loop is None or not self._loop.alive:
                self._start_compliant_loop(tare=False)
            loop = self._loop
            self._compliant_target, self._compliant_speed = target.copy(), speed
        else:
            self._end_motions()
            loop = self._start_loop(pf.ControllerMode.JointImpedance)
        path = loop.move_to(target, speed)
        if not wait and compliant:
            return
        self._watch_stream(loop, target, 2 * path.T + SETTLE_S, compliant)
        if not compliant:
            loop.finish()
            self._loop = None
            if loop.error is not None:
                self._raise_motion_error(loop.error, "move_joints")

    def _watch_stream(self, loop: StreamLoop, target: np.ndarray, budget: float, compliant: bool) -> None:
        """Until the streamed path has ended at rest: stiff, on ``target`` (FOLLOW_TOL, REST_DQ); compliant, the
        tool still for 50 ms where it arrived (or where a contact stopped it). Out of ``budget`` s: stiff, a
        fault (motion ended); compliant, done (the arm stays compliant against what stopped it)."""
        deadline = time.monotonic() + budget
        rest_since = None
        while True:
            if self._interrupt.is_set():  # stop() from another thread ended the motion
                raise SafetyStop(f"{self.where}: move_joints: stopped")
            if loop.error is not None or loop.done.is_set():
                self._loop = None
                self._raise_motion_error(loop.error, "move_joints")
            if loop.path_done():
                s = loop.state
                if not compliant and self._stream_on_target(s, target):
                    return
                if compliant:
                    rest_since = rest_since or time.monotonic()
                    if self._moving(s):
                        rest_since = time.monotonic()
                    elif time.monotonic() - rest_since > 0.05:
                        return
            if time.monotonic() > deadline:
                if compliant:
                    return
                self._end_motions()
                raise DeviceFault(f"{self.where}: move_joints: the arm did not reach its target in time; stopped")
            time.sleep(0.004)

    @staticmethod
    def _stream_on_target(s, target: np.ndarray) -> bool:
        dq = float(np.max(np.abs(np.asarray(s.dq))))
        return float(np.max(np.abs(np.asarray(s.q) - target))) < FOLLOW_TOL and dq < REST_DQ

    def _start_loop(self, mode) -> StreamLoop:
        robot = self._live("move_joints")
        loop = StreamLoop(robot, pf, mode, self.accel, limits.DDDQ_MAX[0] / 10)
        try:
            loop.start()
        except Exception as e:
            self._raise_motion_error(e, "start of the streamed motion")
        self._loop = loop
        return loop

    def _start_compliant_loop(self, tare: bool = True) -> None:
        robot = self._live("set_compliant")
        k, kr = self.stiffness, self.rot_stiffness
        try:
            robot.set_cartesian_impedance([k, k, k, kr, kr, kr])
            if tare or self._tare is None:
                self._tare = np.asarray(robot.read_once().O_F_ext_hat_K, float)[:3]
        except Exception as e:
            raise self._translate(e, "set_compliant") from None
        self._start_loop(pf.ControllerMode.CartesianImpedance)

    def _end_motions(self) -> None:
        """Finish whatever motion runs (the robot then holds where the arm is)."""
        h, self._handler = self._handler, None
        if h is not None:
            with contextlib.suppress(Exception):
                h.stop_control()
        loop, self._loop = self._loop, None
        if loop is not None:
            loop.finish()

    @_frameless
    def jog(self, mode, axis: int, step: float, speed: float | None = None) -> None:
        q0 = self.joint_positions().q
        target, v = self._jog_plan(q0, mode, axis, step, speed, joint_default=self.speed, tool_default=0.05)
        self.move_joints(target, speed=v)

    @_frameless
    def stop(self) -> None:
        """End the running motion; the robot holds the arm where it stands (StopMove when nothing of the
        driver's runs)."""
        self._interrupt.set()
        had = self._handler is not None or self._loop is not None
        self._compliant, self._tare = False, None  # a compliant hold ends too: the robot holds the arm
        self._end_motions()
        if not had and self._robot is not None:
            with contextlib.suppress(Exception):
                self._robot.stop()

    @_frameless
    def enable(self) -> None:
        """Clear a latched reflex (automatic error recovery). Brakes and FCI activation are Desk's."""
        s = self._state("enable")
        if s.robot_mode == pf.RobotMode.Reflex or s.current_errors:
            self._recover("enable")
        elif s.robot_mode == pf.RobotMode.UserStopped:
            raise SafetyStop(f"{self.where}: the user stop is pressed; release it (and the robot returns to idle)")

    @_frameless
    def disable(self) -> None:
        """Stop; the arm stays under the robot's control (locking the brakes is Desk's)."""
        self.stop()

    @_frameless
    def unlock_protective_stop(self, wait: bool = True, timeout: float = 8.0) -> str:
        """Recover from a reflex (the robot's protective stop): ``automatic_error_recovery``."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                self._recover("unlock_protective_stop")
                return "automatic error recovery done"
            except DeviceFault:
                if not wait or time.monotonic() > deadline:
                    raise
                time.sleep(0.25)

    @_frameless
    def set_compliant(self, on: bool) -> None:
        """On: Cartesian impedance (``stiffness`` N/m, ``rot_stiffness`` N m/rad at the end effector) held by the
        driver's 1 kHz loop; moves while compliant are moves of that motion (contact stops them softly). A hold
        the robot aborts for a communication-constraint violation is recovered and taken up again (the last
        compliant target, the force at rest from before), ``retries`` times per compliant phase.
        Off: the motion ends and the robot holds the arm where it rests."""
        if on:
            if self._compliant:
                return
            self._end_motions()
            self._revivals = 0
            self._compliant_target = None
            for attempt in range(self.retries + 1):
                try:
                    self._start_compliant_loop()
                    break
                except _Retry as r:
                    if attempt >= self.retries:
                        raise BusError(f"{self.where}: set_compliant: the impedance motion was aborted "
                                       f"{attempt + 1} times by {r}") from None
                    self._recover(str(r))
            self._compliant = True
            self._press_on()
        else:
            if not self._compliant:
                return
            self._compliant = False
            self._tare = None
            loop, self._loop = self._loop, None
            if loop is not None:
                loop.finish()
                if loop.error is not None and not isinstance(loop.error, TimeoutError):
                    try:
                        self._raise_motion_error(loop.error, "set_compliant(False)")
                    except _Retry as r:  # the hold was lost: clear the reflex, the arm rests where it is
                        self._recover(str(r))

    def _note_move(self, target: np.ndarray) -> None:
        """Remember a stiff move (where from, where to, the external force at rest before it): compliance taken
        up right after it presses on along it (``_press_on``). The force is read at rest (waited for, at most
        0.5 s): the estimate of a moving arm carries its dynamics, and this one is the touch's zero."""
        self._last_move = None
        if self._compliant or self.press_force <= 0:
            return
        s = self._state("move_joints")
        end = time.monotonic() + 0.5
        while self._moving(s) and time.monotonic() < end:
            time.sleep(0.01)
            s = self._state("move_joints")
        self._last_move = (np.asarray(s.q, float), target.copy(), np.asarray(s.O_F_ext_hat_K, float)[:3])

    def _press_on(self) -> None:
        """Compliance right after a stiff move: the seating press (``drivers.franka.press``). The impedance
        target goes on along the move's straight-line tool direction (orientation kept) at 20 mm/s until contact,
        then ``press_force / stiffness`` beyond the contact, and the call returns once the arm rests against what
        stopped it with a steady force.
        The touch's zero is then the force before the move (free of the contact the stiff move may have made:
        a joint servo driving a ball into a cone leaves 3-40 N that the impedance then releases). Travel
        beyond ``press.TRAVEL`` without contact means nothing is there: the press is called off and the arm held
        where it is (``touch()`` stays off, so the seating step reports it)."""
        last, self._last_move = self._last_move, None
        self.last_press = None
        if last is None or time.monotonic() - self._moved_at > press.WINDOW:
            return  # no stiff move just before (a technician turning compliance on after a jog, a failed move)
        q_from, q_to, force_before = last
        q_now = self._q()
        u, why = press.direction(self.model, q_from, q_to, q_now)
        if u is None:
            log.warning("%s: no seating press: %s", self.where, why)
            return
        self._tare = force_before
        plan = press.plan(self.model, q_now, u, press.TRAVEL + self.press_force / self.stiffness)
        for attempt in range(self.retries + 1):
            try:
                self.last_press = self._watch_press(plan, press.joint_speed(plan, q_now))
                return
            except _Retry as r:
                if attempt >= self.retries:
                    raise BusError(f"{self.where}: seating press aborted {attempt + 1} times by {r}; the robot "
                                   "holds where it stopped") from None
                self._recover(str(r))  # the hold taken up again, the touch's zero kept

    def _watch_press(self, plan: press.Press, speed: float) -> str:
        """Stream the press and watch it: the target goes towards ``plan`` (``press.TRAVEL`` + ``press_force /
        stiffness`` beyond the start); once contact is felt it is set ``press_force / stiffness`` beyond where the
        tool is (the push at rest is then ``press_force`` however far the approach went). Returns how it ended
        (``seated``: at rest with a steady force; ``no contact``: ``press.TRAVEL`` without contact, held there;
        ``not settled``: out of time)."""
        if self._loop is None or not self._loop.alive:
            self._start_compliant_loop(tare=False)
        loop = self._loop
        depth = self.press_force / self.stiffness
        self._compliant_target, self._compliant_speed = plan.q.copy(), speed
        deadline = time.monotonic() + 2 * loop.move_to(plan.q, speed).T + SETTLE_S
        settle = press.Settle(self.press_force)
        tare = float((self._tare if self._tare is not None else np.zeros(3)) @ plan.u)
        touched = False
        while True:
            if self._interrupt.is_set():
                raise SafetyStop(f"{self.where}: seating press: stopped")
            if loop.error is not None or loop.done.is_set():
                self._loop = None
                self._raise_motion_error(loop.error, "seating press")
            s = loop.state
            q, dq = np.asarray(s.q, float), np.asarray(s.dq, float)
            travel = plan.travel(self.model.position(q))
            force = float(np.asarray(s.O_F_ext_hat_K, float)[:3] @ plan.u)
            if not touched and force - tare > self.contact_force:  # contact: press_force from here on
                touched = True
                self._compliant_target = press.plan(self.model, q, plan.u, depth).q
                loop.move_to(self._compliant_target, speed)
            elif not touched and travel > press.TRAVEL:
                return self._call_off(loop, q, speed, travel)
            tool_speed = float(np.linalg.norm(self.model.jacobian_q(q).reshape(6, 7)[:3] @ dq))
            if settle.add(time.monotonic(), tool_speed, force) and touched and loop.path_done():
                log.info("%s: seated: pressing %.2f N after %.2f mm", self.where, force - tare, travel * 1e3)
                return "seated"
            if time.monotonic() > deadline:
                log.warning("%s: seating press: the arm did not come to rest (%.1f mm/s, %.2f N)", self.where,
                            tool_speed * 1e3, force - tare)
                return "not settled"
            time.sleep(0.004)

    def _call_off(self, loop: StreamLoop, q: np.ndarray, speed: float, travel: float) -> str:
        """Nothing to seat in: the hold goes back to where the tool is and the call returns once it rests there
        (at most 2 s)."""
        self._compliant_target = q.copy()
        loop.move_to(q, speed)
        log.warning("%s: seating press called off: %.1f mm beyond where the move ended without contact (no socket "
                    "there?); holding compliant where it is", self.where, travel * 1e3)
        end = time.monotonic() + 2.0
        while time.monotonic() < end and not (loop.path_done() and not self._moving(loop.state)):
            time.sleep(0.01)
        return "no contact"

    def _revive_compliance(self) -> None:
        """The compliant hold ended without being asked to (the robot aborted it): for a communication-constraint
        violation, recover and take the hold up again; anything else is raised."""
        loop = self._loop
        err = loop.error if loop is not None else None
        self._loop = None
        try:
            self._raise_motion_error(err, "compliant hold")
        except _Retry as r:
            if self._revivals >= self.retries:
                raise BusError(f"{self.where}: the compliant hold was aborted {self._revivals + 1} times by {r}; "
                               "the robot holds where it stopped") from None
            self._revivals += 1
            self._recover(str(r))  # restarts the hold (the force at rest kept)
            loop = self._loop
            if self._compliant_target is not None and loop is not None:
                # the new hold starts where the arm is, its spring relaxed: a seated ball's push is gone until
                # the target is back. Returned only once it is and the arm rests again (at most 2 s), or the
                # reading that revived the hold (a sample's touch) would see no contact (seen in CI: "touch
                # indicator is off" right after a revival)
                loop.move_to(self._compliant_target, self._compliant_speed)
                end = time.monotonic() + 2.0
                rest = None
                while time.monotonic() < end and loop.alive:
                    if loop.path_done() and not self._moving(loop.state):
                        rest = rest or time.monotonic()
                        if time.monotonic() - rest >= press.STEADY_S:
                            break
                    else:
                        rest = None
                    time.sleep(0.005)

    # ---- errors -------------------------------------------------------------------------------------------
    def _await_standstill(self, timeout: float = 2.0) -> None:
        """After a motion the robot ended: wait (bounded) until the arm has come to rest, so a raised fault leaves
        it stopped."""
        end = time.monotonic() + timeout
        with contextlib.suppress(Exception):
            while time.monotonic() < end and np.max(np.abs(np.asarray(self._robot.read_once().dq))) > REST_DQ:
                time.sleep(0.01)

    def _raise_motion_error(self, err, what: str):
        text = _one_line(err) if err is not None else "motion ended"
        errors = ""  # what the robot reports now (last_motion_errors outlives a recovery: not that one)
        with contextlib.suppress(Exception):
            errors = str(self._robot.read_once().current_errors)
        if COMM_VIOLATION in text or COMM_VIOLATION in errors:
            raise _Retry(COMM_VIOLATION)
        self._await_standstill()
        if isinstance(err, BaseException):
            raise self._translate(err, what, errors)
        if any(w in text for w in NETWORK_WORDS):  # the asynchronous handler reports a lost link as text
            self._drop()
            raise ConnectionLost(f"{self.where}: {what}: connection lost: {text}")
        if any(c in text or c in errors for c in COLLISION):  # the asynchronous handler reports a reflex as text
            raise SafetyStop(f"{self.where}: {what}: collision reflex ({text}); clear the cause, then recover")
        raise DeviceFault(f"{self.where}: {what}: {text}" + (f" ({errors})" if errors else ""))

    def _translate(self, e: BaseException, what: str, errors: str = ""):
        text = _one_line(e)
        if isinstance(e, pf.NetworkException):
            self._drop()
            return ConnectionLost(f"{self.where}: {what}: connection lost: {text}")
        if any(c in text or c in errors for c in COLLISION):
            return SafetyStop(f"{self.where}: {what}: collision reflex ({text}); clear the cause, then recover")
        if isinstance(e, pf.ControlException | pf.CommandException | pf.InvalidOperationException):
            return DeviceFault(f"{self.where}: {what}: {text}")
        if isinstance(e, (ConfigError, LimitError, DeviceFault, BusError, SafetyStop)):
            return e
        return DeviceFault(f"{self.where}: {what}: {type(e).__name__}: {text}")

    # ---- calibration export -------------------------------------------------------------------------------
    def export_calibration(self, result_or_values, folder: str | Path | None = None) -> list[Path]:
        """The robot keeps its kinematics itself (nothing the FCI offers changes them): write the calibrated
        model as a URDF (``fr3_calibrated.urdf``, the tool as its last link), a station model file
        (``fr3_calibrated.yaml``) and the values (``calibration.json``, SI) into ``folder``."""
        from station.kinematics.modelfile import dump_model
        from station.kinematics.urdfexport import urdf_text

        values = _values_of(result_or_values)
        known = {k: v for k, v in values.items() if k in self.model.param_names}
        model = self.model.with_params(known)
        folder = Path(folder or self.export_dir or f"./franka-calibration-{self.serial or 'unknown'}")
        folder.mkdir(parents=True, exist_ok=True)
        name = self.model.name
        note = (f"calibrated by station for serial {self.serial or 'unknown'}; the robot's own model is unchanged "
                "(Franka arms take no kinematic calibration over the FCI)")
        paths = [folder / f"{name}_calibrated.urdf", folder / f"{name}_calibrated.yaml", folder / "calibration.json"]
        paths[0].write_text(urdf_text(model, note=note), encoding="utf-8")
        paths[1].write_text(dump_model(model), encoding="utf-8")
        paths[2].write_text(json.dumps({"format": "station-franka-calibration/1", "units": "SI (m, rad)",
                                        "model": name, "serial": self.serial, "values": known,
                                        "nominal": {k: self.model.param(k) for k in known}}, indent=1),
                            encoding="utf-8")
        self.last_export = paths
        log.warning("%s: robot unchanged; calibrated model exported to %s", self.where, folder)
        return paths


class _Retry(BusError):
    """A motion the robot aborted for a reason a recovery and a new attempt cure (a ``BusError``: should one
    ever get past the retries, it is still one line)."""


def _one_line(e) -> str:
    return " ".join(str(e).split())[:300] if e is not None else ""


def _values_of(result_or_values) -> dict[str, float]:
    if isinstance(result_or_values, dict):
        return {str(k): float(v) for k, v in result_or_values.items()}
    values = getattr(result_or_values, "values", None)
    if callable(values):
        return {k: float(v) for k, v in values("model").items()}
    raise ConfigError("calibration export: expected a CalibrationResult or a {parameter: value} dict")
