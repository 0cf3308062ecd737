"""The emulated controller: one 500 Hz tick that runs the uploaded ur_rtde control script's register
handshake on the simulated world, keeps the safety state, and publishes RTDE output packages.

The controller's own kinematics are the world's *nominal* model (what a real controller believes):
``actual_TCP_pose`` comes from it, ``actual_q`` from the world's encoders."""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import deque

import numpy as np
from station.mocks.ur import state as S
from station.mocks.ur.factory import factory

from station.kinematics.se3 import invert, matrix_to_pose, pose_to_matrix

log = logging.getLogger("station.mocks.ur")

_CONSTANTS = {"speed_scaling": 1.0, "target_speed_fraction": 1.0, "actual_main_voltage": 48.0,
              "actual_robot_voltage": 48.0, "joint_temperatures": [30.0] * 6, "actual_joint_voltage": [48.0] * 6,
              "actual_execution_time": 0.3, "tool_temperature": 30.0}
PERIOD = 0.002  # e-Series controller cycle (500 Hz)
# How far behind schedule the cycle catches up with cycles back to back; further behind (this process was not
# scheduled: a loaded host), controller time slips instead. The real controller never falls behind. A burst of
# cycles compresses controller time while the clients' writes keep arriving in real time: a 0.3 s catch-up
# looked like 0.3 s without a write and fired the 10 Hz RTDE watchdog under a station that had written on time
# (seen under load). Slipping keeps the rate of controller time at most real time, so every gap the watchdog
# sees is one the station really left; the watchdog and the motion stay on one clock (the cycles).
CATCH_UP_S = 0.01
POLYSCOPE = "URSoftware 5.11.1.108318 (Mar 22 2022)"  # an e-Series controller
UNLOCK_DELAY = 5.0  # s: a protective stop cannot be unlocked earlier (as on a real robot)
# How long the arm takes from "power on" to IDLE (joints booted, brakes engaged) and from "brake release" to
# RUNNING. No vendor figure; a real e-Series takes seconds. The world may set them (buses.ur.power_on_s, ...).
POWER_ON_S, BRAKE_RELEASE_S = 1.0, 0.5
MODE_NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
              4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
# joint_mode per robot_mode (RTDE guide: 239 power off, 247 booting, 255 idle, 253 running)
JOINT_MODES = {S.ROBOT_MODE_POWER_OFF: 239, S.ROBOT_MODE_POWER_ON: 247, S.ROBOT_MODE_IDLE: 255,
               S.ROBOT_MODE_RUNNING: 253}


def _take(world, kind: str) -> bool:
    faults = getattr(world, "faults", None)
    if faults is None:
        return False
    try:
        return bool(faults.take(kind, "ur"))
    except TypeError:
        return bool(faults.take(kind))


# ur_rtde control-script command ids by name (``rtde: {command: movej}`` in a world file's fault trigger)
COMMAND_NAMES = {v: k[4:].lower() for k, v in vars(S).items() if k.startswith("CMD_")}


def notice(world, **event) -> None:
    """Report a controller event (``dashboard``, ``script``, ``rtde``) to the world's faults, arming those that
    wait for it (docs/world.md, phase triggers)."""
    faults = getattr(world, "faults", None)
    if faults is not None and hasattr(faults, "waiting") and faults.waiting():
        faults.notice(**event)


UR_NAME = re.compile(r"^ur(\d{1,2})(e?)$", re.IGNORECASE)
DEFAULT_ROBOT_MODEL = "UR5"  # the controller an arm of one's own is emulated on (a real one is always a UR type)


def robot_model_of(model_name: str) -> str:
    """``get robot model`` of a controller for a world model: ``ur5e`` -> ``UR5``. A real controller always
    reports a UR type (dashboard ``get robot model``: UR3, UR5, UR10, UR16, UR20, UR30), so an arm of one's own
    is emulated on a UR5 controller (``buses.ur.robot_model`` chooses another)."""
    m = UR_NAME.match(model_name.strip())
    return f"UR{m.group(1)}" if m else DEFAULT_ROBOT_MODEL


class URController:
    """Registers, safety state, program state and the control-script interpreter. Thread-safe: the
    network handlers call into it under ``self.lock``; the tick thread owns motion."""

    def __init__(self, world, *, serial: str = "20235500001", model_name: str = "ur5e",
                 contact_bit: int = S.DEFAULT_CONTACT_BIT, stall_s: float = 1.0, drop_s: float = 1.0,
                 remote_control: bool = True, robot_model: str | None = None,
                 polyscope: str | None = None, unlock_delay_s: float = UNLOCK_DELAY, calibration: str = "links",
                 power_on_s: float = POWER_ON_S, brake_release_s: float = BRAKE_RELEASE_S) -> None:
        self.world = world
        self.nominal = world.nominal
        self.n = self.nominal.n_joints
        self.serial = serial
        self.model_name = model_name
        # identity as the dashboard reports it: "UR5" for a ur5e world (type without the series letter; the
        # series shows in the PolyScope version), overridable per world file (buses.ur.robot_model/polyscope)
        self.robot_model = str(robot_model or robot_model_of(model_name))
        self.polyscope = str(polyscope or POLYSCOPE)
        self.contact_bit = contact_bit
        self.stall_s, self.drop_s = stall_s, drop_s
        self.unlock_delay_s = unlock_delay_s
        self.remote_control = remote_control
        self.lock = threading.RLock()
        # registers (lower and upper range: 0..47)
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        # watchdog: controller time (s) a client last wrote input_int_register_0. Counted in controller cycles as
        # the real script's rtde_set_watchdog does, so a lagging emulator tick cannot shorten or stretch it
        self.in_int0_written = 0.0
        # controller state
        self.tick_count = 0
        self.late_ticks = 0  # cycles that started after their deadline (host scheduling), for benchmarks
        self.max_late = 0.0
        self.runtime_state = S.STOPPED
        self.program: str | None = None  # name of the running program ("rtde_control")
        self.reg_offset = 0
        self.safety_mode = S.SAFETY_NORMAL
        self.safety_bits = S.SS_NORMAL
        self.pstop_at: float | None = None
        self.estop = False
        # robot_mode: a controller boots with the arm powered off; "power on" -> POWER_ON (joints booting) ->
        # IDLE (brakes engaged) after power_on_s; "brake release" in IDLE -> RUNNING after brake_release_s
        self.mode = S.ROBOT_MODE_POWER_OFF
        self.mode_due: tuple[int, float] | None = None  # (next robot_mode, controller time it is reached)
        self.power_on_s, self.brake_release_s = float(power_on_s), float(brake_release_s)
        # every UR joint has a brake: off RUNNING the arm is held by them and ignores commands
        if hasattr(world, "default_brakes"):
            world.default_brakes(True)
        self._arm_enabled(False)
        self.teach = False
        self.freedrive_axes = [1] * 6
        self.speed_qd: np.ndarray | None = None  # speedj target (rad/s) held until stopped
        self.speed_xd: np.ndarray | None = None  # speedl target (base frame, m/s and rad/s)
        self.sync_busy = False  # a blocking move in progress: the script loop waits for it
        self.async_busy = False
        self.executing = False
        self.watchdog_hz = 0.0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.stall_until = 0.0
        # fault injection (emulator dashboard "hold_scripts S"): programs received before this controller time start
        # only then, as on a controller too busy to start them (what a station sees as a silent script start)
        self.hold_scripts_until = 0.0
        self.pending_program: tuple[str, str] | None = None
        self.messages: list[str] = []
        self.cmd_log: deque[tuple[int, int]] = deque(maxlen=40)  # (tick, command id) written by clients
        self.q_prev = np.asarray(world.encoder_q(), dtype=float)
        self.qd = np.zeros(self.n)
        self._load_kinematics(calibration)
        self.on_drop = None  # set by the server: closes every connection for ``seconds``
        # instant/sim worlds: the controller's cycle is the world's clock (2 ms of world time per tick)
        self._sim = getattr(world, "time_mode", "realtime") != "realtime"
        self._running = False
        self._thread: threading.Thread | None = None
        self._state_cache: dict | None = None
        self._pose_key: tuple | None = None
        self._pose: list[float] = []

    def _load_kinematics(self, calibration: str) -> None:
        """The controller's own kinematics: its factory calibration (kept across a power cycle, like
        calibration.conf); actual_TCP_pose, IK and moveL use it, KinematicsInfo reports its DH rows."""
        self.factory = factory(self.world, calibration)
        self.flange_model = self.factory.model
        names = [n for n in self.nominal.param_names if n.startswith("tcp.")]
        nominal_flange = self.nominal.with_params({n: 0.0 for n in names})
        q0 = np.zeros(self.n)
        # installation TCP = nominal tool (the installation is kept across a power cycle; setTcp is not)
        self.installation_tcp = invert(nominal_flange.fk(q0)) @ self.nominal.fk(q0)
        self.tcp = self.installation_tcp.copy()

    # ---- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self._running = True
        self._thread = threading.Thread(target=self._loop, name="ur-controller", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2)
        self.world.halt()

    def controller_time(self) -> float:
        return self.tick_count * PERIOD

    @property
    def powered(self) -> bool:
        return self.mode in (S.ROBOT_MODE_POWER_ON, S.ROBOT_MODE_IDLE, S.ROBOT_MODE_RUNNING)

    @property
    def mode_name(self) -> str:
        return MODE_NAMES.get(self.mode, str(self.mode))

    # ---- power (dashboard "power on", "brake release", "power off") ------------------------------
    def power_on(self) -> None:
        """Dashboard ``power on``: from POWER_OFF the joints boot (POWER_ON) and reach IDLE after power_on_s.
        In any other mode nothing changes (the reply is the same). Refused while an emergency stop is active."""
        with self.lock:
            if self.mode != S.ROBOT_MODE_POWER_OFF:
                return
            if self.estop:
                self.messages.append("power on refused: emergency stop active")
                return
            self.mode = S.ROBOT_MODE_POWER_ON
            self.mode_due = (S.ROBOT_MODE_IDLE, self.controller_time() + self.power_on_s)
            self.messages.append("powering on")

    def brake_release(self) -> None:
        """Dashboard ``brake release``: only in IDLE (the UR ROS driver's robot_state_helper waits for IDLE before
        it sends it); the arm is RUNNING after brake_release_s. In any other mode it has no effect (strictest
        reading: the documented reply is the same)."""
        with self.lock:
            if self.mode != S.ROBOT_MODE_IDLE or self.mode_due is not None:
                self.messages.append(f"brake release ignored in robot mode {self.mode_name}")
                return
            self.mode_due = (S.ROBOT_MODE_RUNNING, self.controller_time() + self.brake_release_s)
            self.messages.append("releasing brakes")

    def power_off(self) -> None:
        with self.lock:
            self._halt_all()
            self._end_program()
            self.mode, self.mode_due = S.ROBOT_MODE_POWER_OFF, None
            self._arm_enabled(False)
            self.messages.append("powered off")

    def _power_step(self) -> None:
        if self.mode_due is not None and self.controller_time() >= self.mode_due[1]:
            self.mode, self.mode_due = self.mode_due[0], None
            self.messages.append(f"robot mode {self.mode_name}")
            self._arm_enabled(self.mode == S.ROBOT_MODE_RUNNING)

    def _arm_enabled(self, on: bool) -> None:
        """The world's joints powered (RUNNING: brakes released) or held by their brakes."""
        if hasattr(self.world, "set_enabled"):
            self.world.set_enabled(on)

    def power_cycle(self) -> None:
        """The controller reboots: what it keeps on disk stays (serial, factory calibration, installation and its
        TCP, remote-control setting); everything volatile is lost: the arm boots POWER_OFF, no program runs,
        registers, watchdog, speed targets and a protective stop are gone. An emergency stop stays while its
        button is pressed. The arm itself (the world) holds where it stands, on its brakes."""
        with self.lock:
            self._halt_all()
            self._end_program()
            self.program = None
            self.mode, self.mode_due = S.ROBOT_MODE_POWER_OFF, None
            self._arm_enabled(False)
            if self.safety_mode == S.SAFETY_PROTECTIVE_STOP:
                self.safety_mode, self.safety_bits, self.pstop_at = S.SAFETY_NORMAL, S.SS_NORMAL, None
                self.world.clear_protective_stop()
            for bank in (self.in_int, self.out_int):
                bank[:] = [0] * len(bank)
            for bank in (self.in_double, self.out_double):
                bank[:] = [0.0] * len(bank)
            self.tcp = self.installation_tcp.copy()
            self.freedrive_axes = [1] * 6
            self.stall_until = 0.0
            self.hold_scripts_until, self.pending_program = 0.0, None
            self.cmd_log.clear()
            self.messages.append("power cycle: controller rebooted")

    def _loop(self) -> None:
        next_t = time.monotonic()
        self.publishers: list = getattr(self, "publishers", [])
        while self._running:
            try:
                self.tick()
            except Exception:  # a bug in one tick must not freeze the controller: log and stop motion
                log.exception("controller tick failed")
                self.world.halt()
            next_t += PERIOD
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:  # behind schedule: the next packages leave back to back (clients may merge them)
                self.late_ticks += 1
                self.max_late = max(self.max_late, -delay)
                if delay < -CATCH_UP_S:
                    next_t = time.monotonic()  # slip: see CATCH_UP_S

    # ---- one controller cycle ----------------------------------------------------------------
    def tick(self) -> None:
        with self.lock:
            self.tick_count += 1
            if self._sim:
                self.world.advance(PERIOD)
            self._faults()
            if self.pending_program is not None and self.controller_time() >= self.hold_scripts_until:
                program, self.pending_program = self.pending_program, None
                self.load_program(*program)
            self._power_step()
            self._watchdog()
            self._motion_step()
            if self.runtime_state == S.PLAYING and self.program == "rtde_control":
                self._script_step()
            q = np.asarray(self.world.encoder_q(), dtype=float)
            self.qd = (q - self.q_prev) / PERIOD
            self.q_prev = q
            self._state_cache = None
            stalled = time.monotonic() < self.stall_until
        if not stalled:
            for pub in list(getattr(self, "publishers", [])):
                pub.on_tick(self)

    def _faults(self) -> None:
        if _take(self.world, "protective_stop"):
            self.protective_stop("fault injected by the world")
        elif getattr(self.world, "protective_stopped", False) and self.safety_mode == S.SAFETY_NORMAL:
            self.protective_stop("the world stopped the arm")  # e.g. world.protective_stop() called directly
        if _take(self.world, "timeout"):
            self.stall(self.stall_s)
        if _take(self.world, "disconnect"):
            self.drop(self.drop_s)

    def _watchdog(self) -> None:
        if (self.watchdog_hz > 0 and self.runtime_state == S.PLAYING
                and self.controller_time() - self.in_int0_written > 1.0 / self.watchdog_hz):
            self.messages.append("RTDE watchdog expired: program stopped")
            self._halt_all()
            self._end_program()

    # ---- faults and safety -------------------------------------------------------------------
    def protective_stop(self, why: str) -> None:
        with self.lock:
            self._halt_all()
            self.safety_mode = S.SAFETY_PROTECTIVE_STOP
            self.safety_bits = S.SS_PROTECTIVE_STOPPED | S.SS_STOPPED_DUE_TO_SAFETY
            self.pstop_at = time.monotonic()
            self.world.protective_stop(f"UR protective stop: {why}")
            if self.runtime_state == S.PLAYING:
                self.runtime_state = S.PAUSED  # the program is paused, as PolyScope does
            self.messages.append(f"protective stop: {why}")
            log.warning("protective stop: %s", why)

    def emergency_stop(self, on: bool) -> None:
        with self.lock:
            if on:
                self._halt_all()
                self.estop = True
                self.safety_mode = S.SAFETY_ROBOT_EMERGENCY_STOP
                self.safety_bits = S.SS_ROBOT_EMERGENCY_STOPPED | S.SS_EMERGENCY_STOPPED | S.SS_STOPPED_DUE_TO_SAFETY
                self.mode, self.mode_due = S.ROBOT_MODE_POWER_OFF, None
                self._arm_enabled(False)
                self._end_program()
            else:
                self.estop = False
                self.safety_mode, self.safety_bits = S.SAFETY_NORMAL, S.SS_NORMAL

    def unlock_protective_stop(self) -> str:
        with self.lock:
            if self.safety_mode != S.SAFETY_PROTECTIVE_STOP:
                return "Protective stop releasing"  # the real dashboard answers the same when not stopped
            if time.monotonic() - (self.pstop_at or 0.0) < self.unlock_delay_s:
                return (f"Cannot unlock protective stop until {self.unlock_delay_s:g}s after occurrence. "
                        "Always inspect cause of protective stop before unlocking")
            self.safety_mode, self.safety_bits, self.pstop_at = S.SAFETY_NORMAL, S.SS_NORMAL, None
            self.world.clear_protective_stop()
            return "Protective stop releasing"

    def stall(self, seconds: float) -> None:
        self.stall_until = time.monotonic() + seconds
        log.warning("data stream stalled for %.2f s", seconds)

    def drop(self, seconds: float) -> None:
        log.warning("dropping every connection for %.2f s", seconds)
        if self.on_drop is not None:
            threading.Thread(target=self.on_drop, args=(seconds,), daemon=True).start()

    @property
    def stopped_by_safety(self) -> bool:
        return self.safety_mode != S.SAFETY_NORMAL

    def _halt_all(self) -> None:
        self.speed_qd = self.speed_xd = None
        self.world.halt()
        if self.teach:
            self.teach = False
            self.world.set_compliant(False)
        if self.async_busy:
            self.async_busy = False
            self._async_progress(-1)

    # ---- program -----------------------------------------------------------------------------
    def load_program(self, name: str, text: str) -> None:
        """A script arrived on port 30003: it replaces whatever runs (as on the real controller)."""
        notice(self.world, script={"program": name})
        with self.lock:
            if self.controller_time() < self.hold_scripts_until:
                self.pending_program = (name, text)
                self.messages.append(f"program {name!r} held until controller time {self.hold_scripts_until:.3f} s")
                return
            self._halt_all()
            self.program = name
            if name != "rtde_control":
                self.messages.append(f"program {name!r} is not an ur_rtde control script: not executed")
                self.runtime_state = S.STOPPED
                return
            if self.stopped_by_safety:
                self.messages.append("program not started: robot is stopped by safety")
                self.runtime_state = S.STOPPED
                return
            if self.mode != S.ROBOT_MODE_RUNNING:
                # the arm must be powered and its brakes released before a program can run; ur_rtde then gives
                # up with "Failed to start control script, before timeout of 5 seconds"
                self.messages.append(f"program {name!r} not started: robot mode {self.mode_name}, not RUNNING")
                self.runtime_state = S.STOPPED
                return
            self.reg_offset = 24 if "reg_offset_int = 24" in text else 0
            self.executing = False
            self.sync_busy = False
            self.watchdog_hz = 0.0
            self.out_int[self.reg_offset] = S.SCRIPT_READY
            self._async_progress(-1)
            self.runtime_state = S.PLAYING

    def stop_program(self) -> None:
        with self.lock:
            self._halt_all()
            self._end_program()

    def _end_program(self) -> None:
        self.runtime_state = S.STOPPED
        self.sync_busy = False
        self.executing = False
        self.watchdog_hz = 0.0

    # ---- the control script's main loop ------------------------------------------------------
    def _reg_i(self, i: int) -> int:
        return self.in_int[self.reg_offset + i]

    def _reg_d(self, i: int, n: int = 1):
        o = self.reg_offset + i
        return self.in_double[o] if n == 1 else np.array(self.in_double[o:o + n])

    def _out_i(self, i: int, v: int) -> None:
        self.out_int[self.reg_offset + i] = int(v)

    def _out_d(self, i: int, values) -> None:
        for k, v in enumerate(np.atleast_1d(values)):
            self.out_double[self.reg_offset + i + k] = float(v)

    def _script_step(self) -> None:
        if self.sync_busy:
            if self.world.is_moving():
                return
            self.sync_busy = False
            self._out_i(0, S.SCRIPT_DONE)
            return
        cmd = self._reg_i(0)
        if cmd not in (S.CMD_NONE, S.CMD_WATCHDOG) and not (self.executing and cmd not in S.REALTIME_COMMANDS):
            notice(self.world, rtde={"command": COMMAND_NAMES.get(cmd, str(cmd))})
            self._faults()  # a fault armed by this very command bites before the controller acts on it
            if self.runtime_state != S.PLAYING:
                return
        if cmd in S.REALTIME_COMMANDS:
            self._execute(cmd)
            self._out_i(0, S.SCRIPT_READY)
        elif cmd == S.CMD_NONE:
            self.executing = False
            self._out_i(0, S.SCRIPT_READY)
        elif not self.executing:
            self.executing = True
            keep = self._execute(cmd)
            if not keep:
                self._end_program()
                return
            if not self.sync_busy:
                self._out_i(0, S.SCRIPT_DONE)

    def _execute(self, cmd: int) -> bool:
        """Run one command like the control script's ``process_cmd``; False ends the program. A command without
        an entry in ``_COMMANDS`` (payload, force-mode gains, IO, ...) has no effect on the simulated world."""
        if cmd == S.CMD_STOP_SCRIPT:
            self._halt_all()
            return False
        run = self._COMMANDS.get(cmd)
        return run is None or run(self, cmd) is not False

    # ---- the control script's commands (each: False ends the program) -------------------------
    def _speedj(self, cmd: int) -> None:
        self.speed_xd = None
        self.speed_qd = self._reg_d(0, 6)

    def _speedl(self, cmd: int) -> None:
        self.speed_qd = None
        self.speed_xd = self._reg_d(0, 6)

    def _jog_start(self, cmd: int) -> None:
        self.speed_qd = None
        speed, feature = self._reg_d(0, 6), int(self._reg_d(6))
        if feature == 1:  # tool frame -> base frame
            R = self._tcp_T(self.q_prev)[:3, :3]
            speed = np.concatenate([R @ speed[:3], R @ speed[3:]])
        self.speed_xd = speed

    def _servoj(self, cmd: int) -> None:
        self.speed_qd = self.speed_xd = None
        self._command_q(self._reg_d(0, 6), None)

    def _stop_motion(self, cmd: int) -> None:
        self._halt_all()

    def _teach_on(self, cmd: int) -> None:
        self.speed_qd = self.speed_xd = None
        self.world.halt()
        if cmd == S.CMD_FREEDRIVE_MODE:
            self.freedrive_axes = [self._reg_i(1 + k) for k in range(6)]
        self.teach = True
        self.world.set_compliant(True)

    def _teach_off(self, cmd: int) -> None:
        self.teach = False
        self.world.set_compliant(False)

    def _freedrive_status(self, cmd: int) -> None:
        self._out_i(1, 1 if self.teach else 0)

    def _set_tcp(self, cmd: int) -> None:
        self.tcp = pose_to_matrix(self._reg_d(0, 6))

    def _tcp_offset(self, cmd: int) -> None:
        self._out_d(0, matrix_to_pose(self.tcp))

    def _fk_default(self, cmd: int) -> None:
        self._out_d(0, matrix_to_pose(self._tcp_T(self.q_prev)))

    def _fk_args(self, cmd: int) -> None:
        q, tcp = self._reg_d(0, 6), pose_to_matrix(self._reg_d(6, 6))
        self._out_d(0, matrix_to_pose(self.flange_model.fk(q) @ tcp))

    def _inverse_kin(self, cmd: int) -> bool:
        q0 = self._reg_d(6, 6) if cmd == S.CMD_GET_INVERSE_KINEMATICS_ARGS else self.q_prev
        q = self._ik(pose_to_matrix(self._reg_d(0, 6)), q0)
        if q is None:
            self.messages.append("get_inverse_kin: no solution")
            return False  # the script raises: the program stops, as on the robot
        self._out_d(0, q)
        return True

    def _joints_within_limits(self, cmd: int) -> None:
        self._out_i(1, int(bool(self.nominal.within_limits(self._reg_d(0, 6))[0])))

    def _pose_within_limits(self, cmd: int) -> None:
        self._out_i(1, 1)

    def _is_steady(self, cmd: int) -> None:
        self._out_i(1, int(not self.world.is_moving()))

    def _client_protective_stop(self, cmd: int) -> None:
        self.protective_stop("triggerProtectiveStop() from the client")

    def _set_watchdog(self, cmd: int) -> None:
        self.watchdog_hz = float(self._reg_d(0))
        self.in_int0_written = self.controller_time()

    def _steptime(self, cmd: int) -> None:
        self._out_d(0, PERIOD)

    def _q_history(self, cmd: int) -> None:
        self._out_d(0, self.q_prev)

    # ---- motion ------------------------------------------------------------------------------
    def _tcp_T(self, q) -> np.ndarray:
        return self.flange_model.fk(np.asarray(q, float)) @ self.tcp

    def _ik(self, T: np.ndarray, q0) -> np.ndarray | None:
        target = T @ invert(self.tcp)
        res = self.flange_model.ik(target[None], np.asarray(q0, float)[None])
        if not res.ok[0] or not self.nominal.within_limits(res.q[0])[0]:
            return None
        return res.q[0]

    def _command_q(self, q, speed, accel=None) -> bool:
        q = np.asarray(q, float)
        if not (np.all(np.isfinite(q)) and self.nominal.within_limits(q)[0]):
            self.messages.append(f"target {np.round(q, 4).tolist()} outside joint limits: program stopped")
            return False
        self.world.command_q(q, speed=speed, accel=accel if accel and accel > 0 else None)
        return True

    def _move(self, cmd: int) -> bool:
        self.speed_qd = self.speed_xd = None
        vals = self._reg_d(0, 6)
        v, a, asynchronous = float(self._reg_d(6)), float(self._reg_d(7)), self._reg_i(1) == 1
        if cmd == S.CMD_MOVEJ:
            q, speed = vals, v
        else:
            if cmd == S.CMD_MOVEL_FK:
                q = vals
            else:
                q = self._ik(pose_to_matrix(vals), self.q_prev)
                if q is None:
                    self.messages.append("move: target pose has no inverse kinematics solution: program stopped")
                    return False
            # movel / movej_ik with a tool speed: joint-interpolated (not a straight line) at the joint speed
            # that keeps the tool at v; documented emulator simplification
            speed = v if cmd == S.CMD_MOVEJ_IK else self._joint_speed_for_tool(q, v)
        if not self._command_q(q, speed, a if cmd in (S.CMD_MOVEJ, S.CMD_MOVEJ_IK) else None):
            return False
        if asynchronous:
            self.async_busy = True
            self._async_progress(0)
        else:
            self.sync_busy = True
        return True

    def _joint_speed_for_tool(self, q1, v_tool: float) -> float:
        q0 = self.q_prev
        dq = np.asarray(q1) - q0
        lead = float(np.max(np.abs(dq)))
        if lead < 1e-12:
            return float(self.nominal.max_velocity.min())
        s = np.linspace(0, 1, 6)[:, None]
        J = self.flange_model.jacobian_q(q0 + s * dq)[:, :3]
        per = float(np.max(np.linalg.norm(J @ (dq / lead), axis=1))) + 0.1  # lever of the TCP, roughly
        return min(float(self.nominal.max_velocity.min()), v_tool / per)

    def _motion_step(self) -> None:
        if self.async_busy and not self.world.is_moving():
            self.async_busy = False
            self._async_progress(-1)
        if self.stopped_by_safety:
            return
        if self.speed_qd is not None:
            self._speed_joints(self.speed_qd)
        elif self.speed_xd is not None:
            q = self.q_prev
            T, Jq = self.flange_model.fk_and_jacobian_q(q)
            J = Jq[0].copy()
            r = T[0, :3, :3] @ self.tcp[:3, 3]
            skew = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
            J[:3] -= skew @ J[3:]
            self._speed_joints(np.linalg.pinv(J) @ self.speed_xd)

    def _speed_joints(self, qd) -> None:
        qd = np.clip(np.asarray(qd, float), -self.nominal.max_velocity, self.nominal.max_velocity)
        # a speed command that would leave the joint limits within one cycle is a protective stop on the robot
        nxt = self.q_prev + qd * PERIOD * 5
        if not self.nominal.within_limits(nxt)[0]:
            self.protective_stop("joint limit reached in speed mode")
            return
        self.world.command_qd(qd)

    def _async_progress(self, value: int) -> None:
        self.async_wr_count = 0 if self.async_wr_count >= 127 else self.async_wr_count + 1
        if value == 0:
            self.async_op_id = 0 if self.async_op_id >= 127 else self.async_op_id + 1
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out_i(2, reg)

    # ---- published state ---------------------------------------------------------------------
    def robot_status_bits(self) -> int:
        bits = S.RS_POWER_ON if self.powered else 0
        if self.runtime_state == S.PLAYING:
            bits |= S.RS_PROGRAM_RUNNING
        if self.teach:
            bits |= S.RS_TEACH_BUTTON
        return bits

    def _tcp_pose(self) -> list[float]:
        """actual_TCP_pose from the nominal model, cached while the joints do not move (FK is the costly
        part of a cycle)."""
        key = (self.q_prev.tobytes(), self.tcp.tobytes())
        if self._pose_key != key:
            self._pose_key = key
            self._pose = matrix_to_pose(self._tcp_T(self.q_prev)).tolist()
        return self._pose

    def value(self, name: str):
        """One output variable for this cycle (registers by index; the rest computed on demand)."""
        if name.startswith("output_int_register_"):
            return self.out_int[int(name[20:])]
        if name.startswith("output_double_register_"):
            return self.out_double[int(name[23:])]
        if name.startswith("input_int_register_"):
            return self.in_int[int(name[19:])]
        if name.startswith("input_double_register_"):
            return self.in_double[int(name[22:])]
        cache = self._state_cache
        if cache is None:
            cache = self._state_cache = {}
        if name in cache:
            return cache[name]
        v = self._compute(name)
        cache[name] = v
        return v

    def _compute(self, name: str):
        if name == "timestamp":
            return self.controller_time()
        if name in ("actual_q", "target_q"):
            return self.q_prev.tolist()
        if name in ("actual_qd", "target_qd"):
            return self.qd.tolist()
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return self._tcp_pose()
        if name == "actual_digital_input_bits":
            return (1 << self.contact_bit) if self.world.contact() else 0
        if name == "robot_mode":
            return self.mode
        if name == "joint_mode":
            return [JOINT_MODES.get(self.mode, 239)] * 6
        if name in ("safety_mode", "safety_status"):
            return self.safety_mode
        if name == "runtime_state":
            return self.runtime_state
        if name == "robot_status_bits":
            return self.robot_status_bits()
        if name == "safety_status_bits":
            return self.safety_bits
        return _CONSTANTS.get(name)  # None: the publisher sends the type's zero

    def snapshot(self, names=("timestamp", "actual_q", "actual_TCP_pose", "safety_status_bits")) -> dict:
        with self.lock:
            return {n: self.value(n) for n in names}

    def write_inputs(self, names: list[str], values: list) -> None:
        """One RTDE input package from a client."""
        with self.lock:
            for name, v in zip(names, values, strict=True):
                if name.startswith("input_int_register_"):
                    i = int(name.rsplit("_", 1)[1])
                    self.in_int[i] = int(v)
                    if i == self.reg_offset:
                        self.in_int0_written = self.controller_time()
                        if not self.cmd_log or self.cmd_log[-1][1] != int(v):
                            self.cmd_log.append((self.tick_count, int(v)))
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = float(v)

    # ur_rtde control-script command -> what the controller does for it (``_execute``); the commands are
    # ur_rtde's (rtde_control.script, ``process_cmd``), their effects the URScript functions they call
    _COMMANDS = {
        S.CMD_MOVEJ: _move, S.CMD_MOVEJ_IK: _move, S.CMD_MOVEL: _move, S.CMD_MOVEL_FK: _move,
        S.CMD_SPEEDJ: _speedj, S.CMD_SPEEDL: _speedl, S.CMD_JOG_START: _jog_start, S.CMD_SERVOJ: _servoj,
        **dict.fromkeys((S.CMD_SPEED_STOP, S.CMD_SERVO_STOP, S.CMD_STOPJ, S.CMD_STOPL, S.CMD_JOG_STOP,
                         S.CMD_FORCE_MODE_STOP), _stop_motion),
        S.CMD_TEACH_MODE: _teach_on, S.CMD_FREEDRIVE_MODE: _teach_on,
        S.CMD_END_TEACH_MODE: _teach_off, S.CMD_END_FREEDRIVE_MODE: _teach_off,
        S.CMD_GET_FREEDRIVE_STATUS: _freedrive_status,
        S.CMD_SET_TCP: _set_tcp, S.CMD_GET_TCP_OFFSET: _tcp_offset,
        S.CMD_GET_FORWARD_KINEMATICS_DEFAULT: _fk_default, S.CMD_GET_FORWARD_KINEMATICS_ARGS: _fk_args,
        S.CMD_GET_INVERSE_KINEMATICS_DEFAULT: _inverse_kin, S.CMD_GET_INVERSE_KINEMATICS_ARGS: _inverse_kin,
        S.CMD_IS_JOINTS_WITHIN_SAFETY_LIMITS: _joints_within_limits,
        S.CMD_IS_POSE_WITHIN_SAFETY_LIMITS: _pose_within_limits,
        S.CMD_IS_STEADY: _is_steady,
        S.CMD_PROTECTIVE_STOP: _client_protective_stop,
        S.CMD_SET_WATCHDOG: _set_watchdog,
        S.CMD_GET_STEPTIME: _steptime,
        S.CMD_GET_ACTUAL_JOINT_POSITIONS_HISTORY: _q_history,
    }
