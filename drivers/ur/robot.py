"""``ur://HOST[?model=ur5e&power_on=yes&calibration=PATH&export=DIR&contact_bit=16&speed=0.5]``: a Universal
Robots e-Series arm over RTDE (ur_rtde's RTDEReceiveInterface + RTDEControlInterface), the dashboard server and
the primary client interface (its factory calibration) (options: ``URRobot.options``).

Connecting needs no running arm: the dashboard, the RTDE receive stream and the controller's calibration are
read first; the control interface (ur_rtde's control script, which a controller runs only when the arm is
RUNNING) is opened then if the arm is RUNNING, else with the first motion. Powering on and releasing the brakes
happen only where the URL allows it (``power_on=yes``), in the order UR's own ROS driver uses: ``power on``, wait
for IDLE, ``brake release``, wait for RUNNING.

Units: joints in rad, joint speed rad/s, tool speed m/s. Every motion command checks limits first (a refused
command sends nothing) and is then watched: protective/emergency stop -> SafetyStop, lost link ->
ConnectionLost, stalled data stream -> BusError; each leaves the robot stopped. The channels and their supervision
are ``RTDELink`` (drivers/ur/link.py), the controller-side jog watchdog is ``JogWatchdog`` (drivers/ur/watchdog.py);
``URRobot`` composes both."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np
from station.drivers.ur.calibration import (
    _values_of,
    calibrated_table,
    controller_model,
    export_files,
    published_table,
    read_calibration_conf,
    table_from_deltas,
    table_from_rows,
)
from station.drivers.ur.dashboard import DashboardClient
from station.drivers.ur.identity import check_arm
from station.drivers.ur.link import RTDELink
from station.drivers.ur.power import power_up
from station.drivers.ur.primary import read_kinematics
from station.drivers.ur.safety import (
    ROBOT_MODE_RUNNING,
    SS_ESTOP_MASK,
    SS_FAULT,
    SS_HALTED,
    SS_PROTECTIVE,
    SS_VIOLATION,
    mode_name,
    safety_error,
)
from station.drivers.ur.watchdog import MOVE_IDLE_WATCHDOG_HZ, MOVE_WATCHDOG_HZ, JogWatchdog

from station.kinematics import Model
from station.robot.base import CHAIN_OPTIONS, RobotBase
from station.robot.errors import (
    BusError,
    ConfigError,
    ConnectionLost,
    DeviceFault,
    IdentityMismatch,
    LimitError,
    SafetyStop,
)
from station.robot.motion import MANUAL_TOOL_SPEED_CAP, check_joint_limits, joint_speed_for_tool_cap
from station.robot.protocol import Identity, JointSnapshot, JointState, RobotStatus
from station.robot.silence import Silence
from station.robot.url import Option, Options, RobotURL, either, integer, number, text

log = logging.getLogger("station.drivers.ur")

# ur_rtde's own wait for its control script is 5 s; the driver waits itself, counting only what it observed
CONTROL_SCRIPT_TIMEOUT_S = 5.0
LOCAL_HOSTS = ("localhost", "127.0.0.1")  # ur_rtde skips its remote-control check only for these
# RTDE stall timeout: the controller sends a package every 2 ms; 200 ms gave spurious stalls on a loaded
# 2-core PC; 500 ms (250 packages) soaked with zero spurious faults under two busy loops
# (tests/e2e/test_soak_buses.py) and still stops the arm within half a second of a dead link.
STALL_MS = 500.0


def _rows_checksum(table) -> str:
    """A checksum of DH rows the controller did not send one for (a calibration.conf, the published table)."""
    import struct
    import zlib

    rows = np.column_stack([table.theta, table.a, table.d, table.alpha])
    return "-".join(f"{zlib.crc32(struct.pack('>4d', *r)) & 0xFFFFFFFF:08x}" for r in rows)


class URRobot(RobotBase):
    """Fulfils ``station.robot.Robot`` for UR e-Series controllers; capabilities: calibration export (and
    read/write of the ``calibration.conf`` the station uses), contact input, freedrive, Cartesian motion,
    protective-stop unlock, reconnect."""

    vendor = "Universal Robots"
    options = Options(
        Option("model", text(), "ur5e", "kinematic model (`ur3e`, `ur5e`, `ur10e` or a model file)",
               default_doc="`ur5e`"),
        Option("power_on", either("yes", "no"), "no", "`yes`: the station may power the arm on and release its brakes "
               "(dashboard `power on`, wait for IDLE, `brake release`, wait for RUNNING); `no`: an arm that is not "
               "RUNNING is refused before any motion, naming this option"),
        Option("calibration", either("controller", "none", otherwise=text()), "controller", "the station's "
               "nominal model: `controller` reads the factory calibration the controller reports (KinematicsInfo on "
               "the primary interface, port 30001); a path reads a copied `calibration.conf` (`[mounting]` deltas); "
               "`none` uses the published table. The rows are converted to the model with nearly parallel axes "
               "re-intersected; the checksum is journaled with the robot's identity", default_doc="`controller`"),
        Option("export", text(), None, "folder for `write_calibration()` exports",
               default_doc="`./ur-calibration-SERIAL/`"),
        Option("contact_bit", integer(0, 63), 16, "bit of `actual_digital_input_bits` wired to the contact sensor "
               "(0-7 DI, 8-15 CI, 16-17 tool DI)", default_doc="`16` = tool DI 0"),
        Option("speed", number(0, unit="rad/s", open_low=True), None, "default joint speed of `move_joints`, at "
               "most the slowest joint's maximum", default_doc="`0.5`"),
        Option("jog_speed", number(0, unit="rad/s", open_low=True), None, "default joint jog speed, at most the "
               "slowest joint's maximum", default_doc="`0.2`"),
        Option("tool_speed", number(0, MANUAL_TOOL_SPEED_CAP, unit="m/s", open_low=True), 0.05,
               "default tool speed of Cartesian jogs and `move_linear`"),
        Option("jog_watchdog", number(0, 500, unit="Hz"), 10.0, "controller-side RTDE watchdog during speed jogs "
               "(0 = off)"),
        Option("move_watchdog", number(0, 500, unit="Hz"), MOVE_WATCHDOG_HZ, "controller-side RTDE watchdog during "
               "waited moves: a station that dies mid-move stops the arm within its period (0 = off)"),
        Option("serial", text(), None, "serial number to use only if the controller does not report one "
               "(PolyScope < 5.6)"),
        Option("robot_type", text(), None, "the arm a model file is for (`UR5e`, `UR10`, ...), checked against "
               "the controller's `get robot model` + PolyScope series at connect", default_doc="from the model "
               "name (`ur5e` -> UR5 e-Series)"),
        Option("stall_ms", number(20, 10000, unit="ms"), STALL_MS, "RTDE stall timeout: no new 500 Hz package for "
               "this long is a fault (robot stopped); also bounds how long a lost link can go unnoticed inside a "
               "move", default_doc=f"`{STALL_MS:g}` (= 250 packages)"),
        *CHAIN_OPTIONS,
    )

    def __init__(self, host: str, catalog: Model, *, deltas: dict[str, list[float]] | None = None,
                 calibration: str | None = "controller", power_on: bool = False,
                 export_dir: str | None = None, contact_bit: int = 16, speed: float = 0.5, accel: float = 1.0,
                 jog_speed: float = 0.2, tool_speed: float = 0.05, stale_timeout: float = STALL_MS / 1000.0,
                 jog_watchdog: float = 10.0, serial: str | None = None, robot_type: str | None = None,
                 url: str = "", connect: bool = True, move_watchdog: float = 2.0) -> None:
        self.host = host
        self.catalog = catalog  # the arm's published geometry
        self.deltas = deltas  # a copied calibration.conf, if given (calibration=PATH)
        # "controller" (KinematicsInfo), "file" (deltas), None (published table)
        self.calibration_source = "file" if deltas is not None else calibration
        self.power_on = power_on
        self.calibration: dict = {}  # what the nominal model came from: source, checksum, status (journaled)
        self.model: Model = catalog  # replaced by the controller's calibration at connect
        self.export_dir = export_dir
        self.contact_bit = contact_bit
        self.speed, self.accel = speed, accel
        self.jog_speed, self.tool_speed = jog_speed, tool_speed
        self._dash = DashboardClient(host)
        self._link = RTDELink(host, self._dash, stale_timeout, on_abandon=self._speed_ended)
        self.jog_watchdog = jog_watchdog  # Hz: controller-side RTDE watchdog armed for speed jogs (0: off)
        self.move_watchdog = move_watchdog  # Hz: the same during a waited move, kicked by its wait loop (0: off)
        # looked up on the robot at each call: a test (and a subclass) may wrap _bounded
        self._watchdog = JogWatchdog(self._link, lambda *a: self._bounded(*a))
        self.url = url or f"ur://{host}?model={catalog.name}"
        self.url_serial = serial  # used only when the controller does not report one (PolyScope < 5.6)
        self.serial = serial or ""
        self.firmware = ""
        self.robot_model = ""
        self.robot_type = robot_type  # the arm the model is for, when its name does not say (model files)
        self.arm = ""  # what the controller is, e.g. "UR5e" (checked at connect)
        self.last_export: list[Path] = []
        self._compliant_mode: str | None = None  # "freedrive" | "teach"
        self._speeding = False
        self._interrupt = threading.Event()  # set by stop() from any thread: ends a waited move
        self._last_ts: float | None = None
        if connect:
            self.connect()

    # the link's channels and stall timeout under the names the motion code reads them by
    @property
    def stale_timeout(self) -> float:
        """s: the RTDE stall timeout (URL ``stall_ms``)."""
        return self._link.stale_timeout

    @stale_timeout.setter
    def stale_timeout(self, seconds: float) -> None:
        self._link.stale_timeout = seconds

    @property
    def _r(self):
        return self._link.receive

    @property
    def _c(self):
        return self._link.control

    @_c.setter
    def _c(self, control) -> None:
        self._link.control = control

    def _speed_ended(self) -> None:
        self._speeding = False

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def from_url(cls, url: RobotURL, **overrides) -> URRobot:
        o = cls.options.parse(url)
        if not url.host:
            raise ConfigError(f"robot URL {url.raw!r}: ur:// needs the controller's address, e.g. ur://192.168.0.10")
        if url.port is not None:
            raise ConfigError(f"robot URL {url.raw!r}: ur:// takes no port (RTDE 30004, dashboard 29999 and "
                              "script 30003 are fixed by the controller)")
        catalog = cls.load_url_model(url, o["model"], o["tip_link"], o["base_link"])
        cal = o["calibration"]
        deltas = read_calibration_conf(cal, catalog.n_joints) if cal not in ("controller", "none") else None
        vmax = float(catalog.max_velocity.min())
        for key in ("speed", "jog_speed"):  # bounded by the model: checked once it is known
            if o[key] is not None and o[key] > vmax:
                raise ConfigError(f"robot URL {url.raw!r}: {key}={o[key]:g} must be in (0, {vmax:g}] rad/s "
                                  f"(model {catalog.name})")
        args = dict(deltas=deltas, calibration={"controller": "controller", "none": None}.get(cal, "file"),
                    power_on=o["power_on"] == "yes", export_dir=o["export"], contact_bit=o["contact_bit"],
                    speed=o["speed"] or min(0.5, vmax), jog_speed=o["jog_speed"] or min(0.2, vmax),
                    tool_speed=o["tool_speed"], jog_watchdog=o["jog_watchdog"],
                    move_watchdog=o["move_watchdog"], serial=o["serial"],
                    robot_type=o["robot_type"], stale_timeout=o["stall_ms"] / 1000.0, url=url.raw)
        args.update(overrides)
        return cls(url.host, catalog, **args)

    # ---- connection --------------------------------------------------------------------------
    def connect(self) -> None:
        """Dashboard (identity, remote control), RTDE receive stream and the controller's calibration. Nothing
        here needs the arm powered: the control interface opens with the first motion (``_ready_for_motion``)."""
        self._dash.connect()
        self.firmware = self._dash.polyscope_version()
        reported = self._dash.serial_number()
        self.serial = reported if reported.isdigit() else (self.url_serial or "")
        self.robot_model = self._dash.robot_model()
        try:  # before anything else: a model for another arm must never move this one
            self.arm = check_arm(self.host, self.catalog.name, self.robot_type, self.robot_model, self.firmware)
        except Exception:
            self._dash.close()
            raise
        if self.host not in LOCAL_HOSTS and not self._dash.is_in_remote_control():
            self._dash.close()
            raise ConfigError(f"ur://{self.host}: the robot is in local control; switch it to Remote Control on "
                              "the teach pendant (Settings > System > Remote Control, then the pendant's top bar)")
        self._link.open_receive()
        try:
            self._load_calibration()
        except Exception:
            self._link.drop()
            raise
        self._link.control = None
        self._last_ts = None
        self._watchdog.script_started()
        self._link.lost = False
        if int(self._r.getRobotMode()) == ROBOT_MODE_RUNNING and \
                safety_error(self.host, int(self._r.getSafetyStatusBits())) is None:
            # a running arm: take control now, as ur_rtde does (a stale control script of a station that died is
            # stopped and a fresh one started; the teardown stops ours)
            try:
                self._link.open_control()
                self._start_script()
            except Exception:
                self._link.drop()
                raise
        log.info("ur://%s connected: serial %s, %s, robot mode %s", self.host, self.serial, self.firmware,
                 self._mode_name())

    def _load_calibration(self) -> None:
        """The station's nominal model for the session: the controller's factory calibration (or the copied
        calibration.conf, or the published table) converted to the model's convention. On a reconnect the
        controller must report the same calibration as before: the session's samples were taken with it."""
        pub = published_table(self.catalog)
        if self.calibration_source == "controller":
            info = read_kinematics(self.host)
            table = table_from_rows(self.catalog, info.theta, info.a, info.d, info.alpha)
            cal = {"source": "controller", "checksum": info.checksum_text, "status": info.calibration_status}
        elif self.calibration_source == "file":
            table = table_from_deltas(self.catalog, self.deltas)
            cal = {"source": "calibration.conf", "checksum": _rows_checksum(table)}
        else:
            table = pub
            cal = {"source": "published table", "checksum": _rows_checksum(table)}
        if self.calibration and self.calibration.get("checksum") != cal["checksum"]:
            raise IdentityMismatch(f"ur://{self.host}: the controller's calibration changed while the station was "
                                   f"away (checksum {self.calibration['checksum']} -> {cal['checksum']}); the "
                                   "session's samples belong to the old one: start a new session")
        self.model = controller_model(self.catalog, table, source=f"ur://{self.host} ({cal['source']})")
        self.calibration = cal

    def reconnect(self, timeout: float = 10.0) -> None:
        """Re-open every channel after a ConnectionLost (retries until ``timeout`` s)."""
        self._check_open("reconnect")
        self._link.drop()
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.connect()
                return
            except (ConnectionLost, BusError) as e:
                self._link.drop()
                if time.monotonic() > deadline:
                    raise ConnectionLost(f"ur://{self.host}: reconnect failed for {timeout:g} s: {e}") from None
                time.sleep(0.25)

    TEARDOWN_S = 2.0  # s: how long close() keeps trying to stop the program of a controller it lost

    def _shutdown(self) -> None:
        """Stop motion, end the control script on the controller, close every channel. After a link loss (the
        RTDE link dropped, or a hanging call abandoned the control interface) the program is stopped over the
        dashboard instead, retried for TEARDOWN_S (a short outage: the controller's ports come back); a
        controller that stays unreachable is said loudly: its program may still run."""
        # after a link loss the control interface is not trusted (ur_rtde may report a half-reconnected state)
        lost = self._link.lost or self._link.abandoned is not None
        if self._c is not None and not lost:
            try:
                if self._c.isConnected():
                    if self._c.isProgramRunning():
                        self.stop()
                        self._c.stopScript()
                else:
                    lost = True
            except Exception as e:  # closing must not fail (the link may already be gone)
                log.warning("ur://%s: close: %s", self.host, e)
                lost = True
        self._link.drop()
        if lost:
            self._link.stop_program_after_loss(self.TEARDOWN_S)
        self._link.release_abandoned()

    # ---- safety checks -------------------------------------------------------------------------
    def _check_safety(self) -> None:
        err = safety_error(self.host, int(self._r.getSafetyStatusBits()))
        if err is not None:
            self._halt_quietly()
            raise err

    def _why_script_stopped(self, window: float = 0.05) -> None:
        """The control connection can see the script stop a package or two before the receive stream shows
        why (a protective stop pauses the program): watch the safety bits for a few cycles, raise what they say."""
        end = time.monotonic() + window
        while time.monotonic() < end:
            self._check_safety()
            time.sleep(0.004)

    def _halt_quietly(self, dashboard: bool = False) -> None:
        """Leave the robot stopped after a fault, whatever state the link is in. ``dashboard``: stop the
        program over port 29999 (when RTDE data is stale, a control command would wait for its answer)."""
        self._speeding = False
        try:
            if not dashboard and self._c is not None and self._c.isConnected() and self._c.isProgramRunning():
                self._bounded("stopJ", self._c.stopJ, 2.0, False)
                return
        except Exception:  # fall through to the dashboard
            pass
        with contextlib.suppress(ConnectionLost, BusError):
            self._dash.stop_program()

    def _bounded(self, what: str, fn, *args):
        """``fn(*args)``, a ur_rtde command that waits for the controller, within the RTDE stall timeout
        (``RTDELink.bounded``: on expiry the control interface is abandoned and ConnectionLost raised)."""
        return self._link.bounded(what, fn, *args)

    def _kick(self) -> None:
        self._watchdog.kick()

    def _mode_name(self, mode: int | None = None) -> str:
        if mode is None:
            mode = int(self._r.getRobotMode()) if self._r is not None else -1
        return mode_name(mode)

    def _start_script(self) -> None:
        """Upload ur_rtde's control script (a stale one is stopped first) and wait until the controller runs it:
        CONTROL_SCRIPT_TIMEOUT_S of observed time (``Silence``: a busy station PC's own gaps do not count)."""
        self._watchdog.script_started()
        log.info("ur://%s: starting the control script", self.host)
        self._c.reuploadScript()
        silence = Silence()
        while not self._c.isProgramRunning():
            self._link.check()
            if silence.tick() > CONTROL_SCRIPT_TIMEOUT_S:
                raise DeviceFault(f"ur://{self.host}: control-script start timeout: the controller did not run "
                                  f"ur_rtde's control script within {CONTROL_SCRIPT_TIMEOUT_S:g} s (runtime_state "
                                  f"{self._r.getRuntimeState()}, robot mode {self._mode_name()}; {silence.note()}); "
                                  "is the arm RUNNING, in remote control, and no program of the pendant running?")
            time.sleep(0.01)

    def _ready_for_motion(self) -> None:
        self._link.check()
        self._check_safety()
        if int(self._r.getRobotMode()) != ROBOT_MODE_RUNNING:
            power_up(self._link, self.power_on, self._check_safety)
        if self._c is None:
            self._link.open_control()
            self._start_script()
            return
        self._kick()
        if not self._c.isProgramRunning():
            # after an unlock, a dashboard stop or a watchdog stop, the control script must run again
            log.info("ur://%s: control script not running: re-uploading", self.host)
            self._start_script()

    def _script_stopped_while_standing(self) -> bool:
        """After a refused command that was to start a motion: on a package newer than the refusal, the program
        is not running, the arm is RUNNING (powered, brakes off) and no safety stop is active."""
        ts = self._r.getTimestamp()
        silence = Silence()
        while self._r.getTimestamp() == ts and silence.tick() < self.stale_timeout:
            time.sleep(0.002)
        self._link.check()
        return (not self._c.isProgramRunning() and int(self._r.getRobotMode()) == ROBOT_MODE_RUNNING
                and safety_error(self.host, int(self._r.getSafetyStatusBits())) is None)

    def _refused(self, what: str) -> None:
        """A ur_rtde command returned False: say why, leave the robot stopped."""
        self._link.check()
        bits = int(self._r.getSafetyStatusBits())
        err = safety_error(self.host, bits)
        watchdog = self._watchdog.diagnosis()
        self._halt_quietly()
        if err is not None:
            raise err
        raise DeviceFault(f"ur://{self.host}: {what} was not executed by the controller (runtime_state "
                          f"{self._r.getRuntimeState()}, robot_mode {self._r.getRobotMode()}){watchdog}")

    def _restart_after_watchdog(self, what: str, previous_write: float) -> None:
        """A station starved of CPU for a whole watchdog period (a loaded PC) had the arm stopped by the
        controller: say so, then a fresh script (a safety stop found meanwhile is raised instead)."""
        log.warning("ur://%s: the RTDE watchdog (%g Hz) ended the control script %.0f ms after our last write "
                    "(this process was not scheduled); %s on a fresh script", self.host, self._watchdog.hz,
                    (time.monotonic() - previous_write) * 1e3, what)
        self._why_script_stopped()
        self._watchdog.script_started()
        self._ready_for_motion()

    # ---- Robot protocol ----------------------------------------------------------------------
    def identity(self) -> Identity:
        """The controller, and the calibration the session's nominal model came from (its checksum: a changed
        factory calibration is another robot as far as a session's samples are concerned)."""
        device = {"controller": self.robot_model, "software": self.firmware, "serial": self.serial,
                  "calibration": self.calibration.get("source", ""),
                  "calibration_checksum": self.calibration.get("checksum", "")}
        if "status" in self.calibration:
            device["calibration_status"] = self.calibration["status"]
        return Identity(vendor=self.vendor, model=self.model.name, serial=self.serial, firmware=self.firmware,
                        serial_source="robot" if self.serial and self.serial != self.url_serial else "url",
                        devices=(device,), url=self.url)

    def joint_positions(self) -> JointSnapshot:
        """actual_q of one RTDE package produced after this call began, with that package's controller
        timestamp (waits at most one 2 ms cycle). None within ``stale_timeout`` -> BusError, robot stopped."""
        self._link.check()
        silence = Silence()  # a loaded station PC's own gaps are not counted against the stream
        ts_entry = self._r.getTimestamp()
        while True:
            ts1 = self._r.getTimestamp()
            q = self._r.getActualQ()
            ts2 = self._r.getTimestamp()
            if ts1 == ts2 and ts1 != ts_entry:
                break
            if silence.tick() > self.stale_timeout:
                self._link.check()
                self._halt_quietly(dashboard=True)
                raise BusError(f"ur://{self.host}: RTDE stall timeout: no new package for "
                               f"{self.stale_timeout * 1e3:.0f} ms (last controller time {ts2:.3f} s; "
                               f"{silence.note()}); RTDE data stream stalled, robot stopped")
            time.sleep(0.0003)
        self._last_ts = ts1
        qa = np.asarray(q, dtype=float)
        return JointSnapshot(q=qa, raw=tuple(float(x) for x in q), raw_unit="rad", t=time.time(), t_device=ts1)

    def tcp_pose(self) -> np.ndarray:
        """The controller's own ``actual_TCP_pose`` (x, y, z m; rx, ry, rz rotation vector), from ITS model."""
        self._link.check()
        return np.asarray(self._r.getActualTCPPose(), dtype=float)

    def move_joints(self, q, speed: float | None = None, wait: bool = True) -> None:
        target = self._checked_target(q, "move_joints")
        v = self._checked_speed(speed, "move_joints", "rad/s", float(self.model.max_velocity.min())) or self.speed
        if not wait:
            self._watchdog.disarm()  # nobody kicks while an unwatched move runs
        self._interrupt.clear()
        self._ready_for_motion()
        self._move(target, v, wait)

    def _move(self, target: np.ndarray, v: float, wait: bool, watch: bool = True) -> None:
        start = self.joint_positions().q
        watch = wait and watch and self.move_watchdog > 0
        if watch:  # ur_rtde's script runs a moveJ to its end without a client: the watchdog stops a dead station's
            self._watchdog.arm(self.move_watchdog)
        previous = self._watchdog.last_write
        sent = time.monotonic()
        ok = self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True)
        self._watchdog.wrote(sent)
        if not ok and self._watchdog.ended_script(previous):
            # between the check before this move and the move (seen on a loaded CI host)
            self._restart_after_watchdog("moveJ is sent again", previous)
            ok = self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True)
            self._watchdog.wrote()
        elif not ok and self._script_stopped_while_standing():
            # stopped from outside (dashboard, pendant) while the arm stood, and this process's RTDE state did
            # not show it yet when it checked before the move (a loaded host's receive thread lags): the script
            # is started again, as the check would have done, and the move sent once more
            log.warning("ur://%s: the control script had stopped before the move (runtime_state %s); started "
                        "again", self.host, self._r.getRuntimeState())
            self._start_script()
            if watch:
                self._watchdog.arm(self.move_watchdog)
            ok = self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True)
            self._watchdog.wrote()
        if not ok:
            self._refused("moveJ")
        if wait:
            lead = float(np.max(np.abs(target - start)))
            self._wait_move(target, lead / v + 2 * v / self.accel + 5.0, v if watch else None)
            if watch and self._watchdog.armed:  # standing, nothing kicks until the next command: relaxed, not
                self._watchdog.arm(MOVE_IDLE_WATCHDOG_HZ)  # ended (a script start per move is slow on a busy PC)

    def _resend_after_watchdog(self, target: np.ndarray, v: float) -> None:
        """The move watchdog ended the script because this process did not kick it for a whole period (a loaded
        PC): a fresh script, the move watchdog again, and the same moveJ from where the arm stopped."""
        self._restart_after_watchdog("the move is finished", self._watchdog.last_write)
        self._watchdog.arm(self.move_watchdog)
        if not self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True):
            self._refused("moveJ")
        self._watchdog.wrote()

    def move_linear(self, pose, speed: float | None = None, wait: bool = True) -> None:
        """UR-specific: ``moveL`` of the controller's TCP to ``pose`` (x, y, z m; rx, ry, rz rotation vector, base
        frame, as ``tcp_pose()``) at ``speed`` m/s (<= 1 m/s; default ``tool_speed``). The target must be
        reachable within joint limits on the station's model, else LimitError and nothing is sent."""
        from station.kinematics.se3 import pose_to_matrix

        p = np.asarray(pose, dtype=float).reshape(-1)
        if p.shape != (6,) or not np.all(np.isfinite(p)):
            raise LimitError(f"move_linear: pose must be 6 finite numbers (x, y, z, rx, ry, rz), got {p.tolist()}")
        self._check_open("move_linear")
        v = self._checked_speed(speed, "move_linear", "m/s", 1.0) or self.tool_speed
        q0 = self.joint_positions().q
        res = self.model.ik(pose_to_matrix(p)[None], q0[None])
        if not res.ok[0]:
            raise LimitError(f"move_linear: pose {np.round(p, 4).tolist()} is not reachable; nothing was sent")
        check_joint_limits(self.model, res.q[0], "move_linear")
        if not wait:
            self._watchdog.disarm()
        self._ready_for_motion()
        if not self._bounded("moveL", self._c.moveL, p.tolist(), v, 0.5, True):
            self._refused("moveL")
        if wait:
            dist = float(np.linalg.norm(p[:3] - self.tcp_pose()[:3]))
            self._wait_move(None, dist / v + 2 * v / 0.5 + 5.0)
            err = float(np.linalg.norm(self.tcp_pose()[:3] - p[:3]))
            if err > 1e-4:
                self._halt_quietly()
                raise DeviceFault(f"ur://{self.host}: moveL ended {err * 1e3:.3f} mm from its target")

    def _wait_move(self, target: np.ndarray | None, budget: float, resend_v: float | None = None) -> None:
        # The budget (planned motion + margin) runs on the controller's clock (RTDE timestamp): the motion
        # runs on that clock, which on a real UR is wall time, so nothing is loosened there; an emulated
        # controller starved of CPU (busy CI machine) runs its world slower and cannot use up a wall-clock
        # budget while the arm is still on plan. A stream that stops advancing is caught on the wall clock
        # by the RTDE stall timeout, as everywhere else (station.robot.silence: not counting the station's own
        # scheduling gaps, seen as a spurious 500 ms stall at load 4 on 2 cores).
        t_start = self._r.getTimestamp()
        ts_seen, silence = t_start, Silence()
        while True:
            if self._interrupt.is_set():
                raise SafetyStop(f"ur://{self.host}: move interrupted by stop(); the arm holds where it stopped")
            self._link.check_moving()
            self._check_safety()
            if not self._c.isProgramRunning():
                if resend_v is not None and self._watchdog.ended_script(self._watchdog.last_write):
                    self._resend_after_watchdog(target, resend_v)  # this process was not scheduled: not a fault
                    continue
                self._why_script_stopped()
                self._halt_quietly()
                raise DeviceFault(f"ur://{self.host}: the control script stopped during the move")
            if self._c.getAsyncOperationProgress() < 0:
                break
            self._kick()
            ts = self._r.getTimestamp()
            if ts != ts_seen:
                ts_seen = ts
                silence.reset()
            elif silence.tick() > self.stale_timeout:
                self._halt_quietly(dashboard=True)
                raise BusError(f"ur://{self.host}: RTDE stall timeout: data stream stalled during the move, no new "
                               f"package for {self.stale_timeout * 1e3:.0f} ms (last controller time {ts:.3f} s; "
                               f"{silence.note()}); robot stopped")
            if ts - t_start > budget:
                self._halt_quietly()
                raise BusError(f"ur://{self.host}: move not finished within {budget:.1f} s (controller time); "
                               "robot stopped")
            time.sleep(0.004)
        # the receive connection may be a package behind the control connection that saw the end of the
        # move: read a package two cycles newer than the newest one at that moment
        ts_done = self._r.getTimestamp()
        snap = self.joint_positions()
        while snap.t_device < ts_done + 0.0039:
            snap = self.joint_positions()
        q = snap.q
        self._check_safety()
        if target is None:
            return
        err = float(np.max(np.abs(q - target)))
        if err > 1e-3:
            self._halt_quietly()
            raise DeviceFault(f"ur://{self.host}: move ended {math.degrees(err):.3f} deg from its target")

    def jog(self, mode: str, axis: int, step: float, speed: float | None = None) -> None:
        """One jog step with speedJ (joints, Cartesian rotations) or speedL (Cartesian translations), watched
        by a deadline; the tool never exceeds 0.25 m/s. Ends with a short moveJ onto the exact target."""
        q0 = self.joint_positions().q
        target = self._jog_target(q0, mode, axis, step)
        if mode == "cartesian" and axis < 3:
            v = self._checked_speed(speed, "jog", "m/s", MANUAL_TOOL_SPEED_CAP) or self.tool_speed
        elif mode == "cartesian":
            v = joint_speed_for_tool_cap(self.model, q0, target, None)
        else:
            v = self._checked_speed(speed, "jog", "rad/s", float(self.model.max_velocity[axis])) or self.jog_speed
        self._ready_for_motion()
        if mode == "cartesian" and axis < 3:
            p0 = self.model.position(q0)
            sign = math.copysign(1.0, step)
            xd = [0.0] * 6
            xd[axis] = sign * v
            a = 0.5  # m/s^2
            self._velocity_jog(lambda: self._bounded("speedL", self._c.speedL, xd, a, 0.0),
                               lambda q: abs(step) - sign * (self.model.position(q) - p0)[axis], v, a)
            v_fix = joint_speed_for_tool_cap(self.model, self.joint_positions().q, target, self.jog_speed)
        else:
            dq = target - q0
            lead = float(np.max(np.abs(dq)))
            if lead <= 0:
                return
            v = joint_speed_for_tool_cap(self.model, q0, target, v)
            u = dq / lead
            qd = (u * v).tolist()
            self._velocity_jog(lambda: self._bounded("speedJ", self._c.speedJ, qd, self.accel, 0.0),
                               lambda q: lead - float(np.dot(q - q0, u)), v, self.accel)
            v_fix = v
        self._move(target, max(min(v_fix, self.jog_speed), 1e-3), True, watch=False)  # under the jog's watchdog

    def jog_velocity(self, mode: str, axis: int, velocity: float, frame: str = "base") -> None:
        """Non-blocking velocity jog for hold-to-run: speedJ (``mode="joint"``, ``velocity`` rad/s on joint
        ``axis``) or speedL (``mode="cartesian"``, axis 0-2 m/s along x/y/z, 3-5 rad/s about x/y/z of the base
        or tool ``frame``). Returns at once; the controller keeps the speed until the next call, ``stop()``, or
        its RTDE watchdog: every call writes the command register, which is what the watchdog watches, so the
        caller must re-send within 1/jog_watchdog s (0.1 s at the default 10 Hz) or the controller stops the
        program by itself (a dead station or network cannot leave the arm running). The tool never exceeds
        0.25 m/s (manual mode) and no joint exceeds the model's limit: a faster request is scaled down."""
        if mode not in ("joint", "cartesian") or frame not in ("base", "tool"):
            raise ConfigError(f"ur://{self.host}: jog_velocity: mode must be joint|cartesian, frame base|tool")
        n = self.model.n_joints
        if not (0 <= axis < (n if mode == "joint" else 6)) or not math.isfinite(velocity):
            raise LimitError(f"ur://{self.host}: jog_velocity: bad axis {axis} or velocity {velocity}")
        q = self.joint_positions().q
        J = np.asarray(self.model.jacobian_q(q), float).reshape(6, n)  # base-frame linear; angular rows
        if mode == "joint":
            qd = np.zeros(n)
            qd[axis] = velocity
        else:
            xd = np.zeros(6)
            xd[axis] = velocity
            if frame == "tool":
                R = self.model.fk(q)[:3, :3]
                xd = np.concatenate([R @ xd[:3], R @ xd[3:]])
            qd = np.linalg.pinv(J) @ xd
        # scale the whole command so neither a joint limit nor the tool cap is exceeded
        lim = np.asarray(self.model.max_velocity, float)
        scale = min(1.0, float(np.min(lim / np.maximum(np.abs(qd), 1e-12))))
        tool = float(np.linalg.norm(J[:3] @ qd))
        if tool > MANUAL_TOOL_SPEED_CAP:
            scale = min(scale, MANUAL_TOOL_SPEED_CAP / tool)
        self._ready_for_motion()
        if mode == "joint":
            self._send_speed(lambda: self._bounded("speedJ", self._c.speedJ, (qd * scale).tolist(), self.accel, 0.0))
        else:
            self._send_speed(lambda: self._bounded("speedL", self._c.speedL, (xd * scale).tolist(), 0.5, 0.0))

    def _send_speed(self, send) -> None:
        """A speed command (``send()`` -> ur_rtde's answer) under the jog watchdog. When the watchdog ended the
        standing script between the check before it and the command (a refresh late by a whole period on a
        loaded station PC), the controller had already stopped the arm: restart the script once and send again,
        with a warning. Refused otherwise (``DeviceFault``, robot stopped)."""
        self._watchdog.arm(self.jog_watchdog)
        self._speeding = True
        previous = self._watchdog.last_write
        sent = time.monotonic()
        ok = send()
        self._watchdog.speed_written(sent)
        if not ok and self._watchdog.ended_script(previous):
            self._restart_after_watchdog("the speed command is sent again", previous)
            self._watchdog.arm(self.jog_watchdog)
            sent = time.monotonic()
            ok = send()
            self._watchdog.speed_written(sent)
        if not ok:
            self._speeding = False
            self._refused("speed command")

    def jog_keep_alive(self) -> None:
        """Between velocity jogs: feed the jog watchdog (armed for the control script's lifetime) while no
        speed command runs, so the controller does not end the program a watchdog period after each stop.
        The arm stands still (speedStop was sent); if this process dies the watchdog ends an idle program."""
        if self._watchdog.armed and not self._speeding:
            self._link.check()
            self._kick()

    def _velocity_jog(self, send, remaining, v: float, a: float) -> None:
        total = remaining(self.joint_positions().q)
        # the step's deadline runs on the controller's clock, as _wait_move's budget does: wall time on a real
        # UR; an emulated controller starved of CPU runs its world (and its watchdog) slower
        budget = total / v + v / a + 1.0
        t_start = self._r.getTimestamp()
        self._speeding = True
        try:
            # if this process or the network dies mid-jog, the controller stops the program itself
            # (the script's rtde_set_watchdog(..., "stop")); it stays armed until the program ends
            self._send_speed(send)
            while True:
                self._link.check_moving()
                snap = self.joint_positions()
                self._check_safety()
                if remaining(snap.q) <= v * v / (2 * a) + v * 0.004:
                    break
                if not self._c.isProgramRunning():
                    if not self._watchdog.ended_script(self._watchdog.last_write):
                        self._why_script_stopped()  # a safety stop says so; else a stop nobody here asked for
                        self._speeding = False
                        raise DeviceFault(f"ur://{self.host}: the control script stopped during the jog (not by "
                                          "the station); the arm holds where it stopped")
                    # this process was kept from kicking the watchdog for a whole period: the arm stands, and the
                    # step is finished with its move
                    self._restart_after_watchdog("the step is finished with a move", self._watchdog.last_write)
                    break
                if self._r.getTimestamp() - t_start > budget:
                    raise BusError(f"ur://{self.host}: jog watchdog: the step did not complete in {budget:.1f} s "
                                   "(controller time); stopped")
                self._kick()
                time.sleep(0.002)
        finally:
            if self._speeding:
                self._speeding = False
                try:
                    if self._bounded("speedStop", self._c.speedStop, a * 4):
                        self._watchdog.wrote()
                    # the arm stands: relax the armed 10 Hz watchdog, or a late first kick of the fix move that
                    # follows a step ends the script under it (moveJ refused, runtime_state STOPPED: seen in CI)
                    self._watchdog.to_idle()
                except Exception:
                    self._halt_quietly()

    def stop(self) -> None:
        self._interrupt.set()
        self._link.check()
        try:
            if self._r.getSafetyStatusBits() & SS_HALTED:
                return  # already halted by the safety system; commands would be refused
            if self._c is not None and self._c.isProgramRunning():
                if self._speeding:
                    if self._bounded("speedStop", self._c.speedStop, 10.0):
                        self._watchdog.wrote()
                    self._speeding = False
                    self._watchdog.to_idle()
                self._bounded("stopJ", self._c.stopJ, 2.0, False)
            elif any(abs(v) > 1e-4 for v in self._r.getActualQd()):
                self._dash.stop_program()
        except (ConnectionLost, BusError):
            raise
        except Exception as e:
            self._halt_quietly()
            raise DeviceFault(f"ur://{self.host}: stop: {e}") from None

    def enable(self) -> None:
        """The arm RUNNING (powered on and brakes released: only with ``power_on=yes``, see
        ``drivers/ur/power.py``) and the control script running."""
        self._link.check()
        self._ready_for_motion()

    def disable(self) -> None:
        self.stop()
        self._dash.power_off()

    def status(self) -> RobotStatus:
        self._link.check()
        bits = int(self._r.getSafetyStatusBits())
        mode = int(self._r.getRobotMode())
        qd = np.asarray(self._r.getActualQd(), dtype=float)
        moving = bool(np.any(np.abs(qd) > 1e-4))
        enabled = mode == ROBOT_MODE_RUNNING
        faults = []
        if bits & (SS_VIOLATION | SS_FAULT):
            faults.append(f"safety fault (safety_status_bits 0x{bits:x})")
        joints = tuple(JointState(j.name, enabled, bool(abs(qd[i]) > 1e-4)) for i, j in enumerate(self.model.joints))
        return RobotStatus(enabled=enabled, moving=moving, faults=tuple(faults), estop=bool(bits & SS_ESTOP_MASK),
                           protective_stop=bool(bits & SS_PROTECTIVE), compliant=self._compliant_mode is not None,
                           joints=joints)

    def touch(self) -> bool:
        """Contact sensor on ``actual_digital_input_bits`` bit ``contact_bit`` (default 16 = tool DI 0)."""
        self._link.check()
        return bool((int(self._r.getActualDigitalInputBits()) >> self.contact_bit) & 1)

    def set_compliant(self, on: bool) -> None:
        """Freedrive (falls back to teach mode) so the tip can settle in a socket; off keeps the position."""
        if not on and self._compliant_mode is None:  # nothing to end; a safety stop is still said (teardown)
            self._link.check()
            self._check_safety()
            return
        if on:
            # the arm rests in freedrive without kicks: a jog watchdog's script is ended; the relaxed one a waited
            # move leaves (MOVE_IDLE_WATCHDOG_HZ) is kept (ending the script before every seat, then starting a
            # fresh one, timed out now and then)
            self._watchdog.disarm()
        self._ready_for_motion()
        if on:
            if self._compliant_mode is not None:
                return
            # bounded like every command that waits for the controller: a link lost here would block in ur_rtde's
            # reconnect loop for minutes (seen in the fault matrix: UR x disconnect while seated)
            if self._bounded("freedriveMode", self._c.freedriveMode):
                self._compliant_mode = "freedrive"
            elif self._bounded("teachMode", self._c.teachMode):
                self._compliant_mode = "teach"
            else:
                self._refused("freedrive/teach mode")
        else:
            if self._compliant_mode is None:
                return
            ok = (self._bounded("endFreedriveMode", self._c.endFreedriveMode) if self._compliant_mode == "freedrive"
                  else self._bounded("endTeachMode", self._c.endTeachMode))
            self._compliant_mode = None
            if not ok:
                self._refused("end of freedrive")

    def unlock_protective_stop(self, wait: bool = True, timeout: float = 8.0) -> str:
        """Dashboard ``unlock protective stop`` (the controller refuses it for 5 s after the stop; with
        ``wait`` this retries until ``timeout``), then restart the control script."""
        deadline = time.monotonic() + timeout
        while True:
            ok, reply = self._dash.unlock_protective_stop()
            if ok:
                break
            if not wait or time.monotonic() > deadline:
                raise SafetyStop(f"ur://{self.host}: unlock refused: {reply}")
            time.sleep(0.25)
        self._dash.close_safety_popup()
        self._compliant_mode = None
        t_end = time.monotonic() + 1.0
        while self._r.getSafetyStatusBits() & SS_PROTECTIVE and time.monotonic() < t_end:
            time.sleep(0.005)
        self._ready_for_motion()
        return reply

    # ---- calibration -------------------------------------------------------------------------
    def read_calibration(self) -> dict[str, float]:
        """The joint zero corrections of the session's nominal model (the controller's calibration converted,
        see ``calibration=``): ``offset.jN`` (rad)."""
        return {f"offset.j{i + 1}": self.model.param(f"offset.j{i + 1}") for i in range(self.model.n_joints)}

    def export_calibration(self, result_or_values, folder: str | Path | None = None) -> list[Path]:
        """Write calibration.conf (the ``[mounting]`` deltas a controller would hold for the calibrated model),
        ur_kinematics.yaml and ur_calibrated.urdf. ``result_or_values``: a CalibrationResult or absolute values
        of this session's model parameters."""
        values = _values_of(result_or_values)
        known = {k: v for k, v in values.items() if k in self.model.param_names}
        calibrated = self.model.with_params(known)
        # what a calibration.conf cannot hold: the mounting, the tool, compliance, and a flange tilt
        dropped = sorted(k for k in values if k not in known or (
            k.split(".", 1)[0] in ("base", "tcp", "compliance") and abs(known[k] - self.model.param(k)) > 0))
        flange = calibrated_table(self.catalog, calibrated).flange
        if np.max(np.abs(flange - published_table(self.catalog).flange)) > 1e-12:
            dropped.append("flange tilt (last link beta)")
        folder = Path(folder or self.export_dir or f"./ur-calibration-{self.serial or 'unknown'}")
        self.last_export = export_files(self.catalog, calibrated, folder, serial=self.serial or "unknown",
                                        dropped=dropped)
        return self.last_export

    def write_calibration(self, values: dict[str, float]) -> None:
        """UR controllers keep their calibration internally: nothing is written to the robot. The values are
        exported (see export_calibration) into URL ``export=DIR`` (default ./ur-calibration-SERIAL/) and
        read back through the written calibration.conf, converted as at connect."""
        paths = self.export_calibration(values)
        deltas = read_calibration_conf(paths[0], self.model.n_joints)
        back = controller_model(self.catalog, table_from_deltas(self.catalog, deltas), source=str(paths[0]))
        for name, v in values.items():
            if name.startswith("offset.j") and name in back.param_names and abs(back.param(name) - v) > 1e-9:
                raise DeviceFault(f"export read-back of {paths[0]}: {name} {back.param(name)!r} != {v!r}")
        log.warning("ur://%s: UR controller unchanged; calibration exported to %s (calibration.conf, URDF, YAML). "
                    "Use it as the nominal with ur://%s?calibration=%s", self.host, paths[0].parent, self.host,
                    paths[0])
