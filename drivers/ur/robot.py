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
ConnectionLost, stalled data stream -> BusError; each leaves the robot stopped."""

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
from station.drivers.ur.primary import read_kinematics

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
from station.robot.registry import bus_library
from station.robot.silence import Silence
from station.robot.url import Option, Options, RobotURL, either, integer, number, text

with bus_library("ur-rtde"):
    import rtde_control
    import rtde_receive

log = logging.getLogger("station.drivers.ur")

# The receive recipe: only what the driver reads (fewer bytes per 2 ms package than ur_rtde's default).
RECV_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_digital_input_bits",
                  "robot_mode", "safety_mode", "runtime_state", "robot_status_bits", "safety_status_bits"]

SS_PROTECTIVE, SS_SAFEGUARD, SS_ESTOP_MASK = 1 << 2, 1 << 4, (1 << 5) | (1 << 6) | (1 << 7)
SS_VIOLATION, SS_FAULT = 1 << 8, 1 << 9
ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 4, 5, 7
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
# ur_rtde's own wait for its control script is 5 s; the driver waits itself, counting only what it observed
CONTROL_SCRIPT_TIMEOUT_S = 5.0
# power on -> IDLE and brake release -> RUNNING: UR's client library waits up to 300 s / 30 s (counted in polls)
POWER_ON_TIMEOUT_S, BRAKE_RELEASE_TIMEOUT_S = 60.0, 30.0
LOCAL_HOSTS = ("localhost", "127.0.0.1")
# RTDE stall timeout: the controller sends a package every 2 ms; 200 ms gave spurious stalls on a loaded
# 2-core PC (issue 15); 500 ms (250 packages) soaked with zero spurious faults under two busy loops
# (tests/test_soak_buses.py) and still stops the arm within half a second of a dead link.
STALL_MS = 500.0  # ur_rtde skips its remote-control check only for these
MOVE_WATCHDOG_HZ = 2.0  # the RTDE watchdog during a waited move: a killed station's arm stops within 0.5 s
MOVE_IDLE_WATCHDOG_HZ = 0.01  # between waited moves (100 s): an expiry only means a fresh script next time
JOG_IDLE_WATCHDOG_HZ = 1.0  # the RTDE watchdog between velocity jogs (arm standing; jog_keep_alive feeds it)


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
        self.stale_timeout = stale_timeout
        self.jog_watchdog = jog_watchdog  # Hz: controller-side RTDE watchdog armed for speed jogs (0: off)
        self.move_watchdog = move_watchdog  # Hz: the same during a waited move, kicked by its wait loop (0: off)
        # the RTDE watchdog the running control script carries (0: none); JOG_IDLE_WATCHDOG_HZ between jogs
        self._watchdog_hz = 0.0
        self._rt_sent = self._last_kick = 0.0
        self._last_write = 0.0  # monotonic: our last write to the command register (what the watchdog watches)
        self.url = url or f"ur://{host}?model={catalog.name}"
        self.url_serial = serial  # used only when the controller does not report one (PolyScope < 5.6)
        self.serial = serial or ""
        self.firmware = ""
        self.robot_model = ""
        self.robot_type = robot_type  # the arm the model is for, when its name does not say (model files)
        self.arm = ""  # what the controller is, e.g. "UR5e" (checked at connect)
        self.last_export: list[Path] = []
        self._r = None
        self._c = None
        self._dash = DashboardClient(host)
        self._compliant_mode: str | None = None  # "freedrive" | "teach"
        self._speeding = False
        self._interrupt = threading.Event()  # set by stop() from any thread: ends a waited move
        self._last_ts: float | None = None
        if connect:
            self.connect()

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
        try:
            self._r = rtde_receive.RTDEReceiveInterface(self.host, -1.0, RECV_VARIABLES)
        except Exception as e:
            self._dash.close()
            raise ConnectionLost(f"ur://{self.host}: RTDE (port 30004) connection failed: {e}") from None
        try:
            self._load_calibration()
        except Exception:
            self._drop_interfaces()
            raise
        self._c = None
        self._last_ts = None
        self._watchdog_hz = 0.0
        self._link_lost = False
        if int(self._r.getRobotMode()) == ROBOT_MODE_RUNNING and \
                self._safety_error(int(self._r.getSafetyStatusBits())) is None:
            # a running arm: take control now, as ur_rtde does (a stale control script of a station that died is
            # stopped and a fresh one started; the teardown stops ours)
            try:
                self._open_control()
                self._start_script()
            except Exception:
                self._drop_interfaces()
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

    def _drop_interfaces(self) -> None:
        # ur_rtde's disconnect() waits 0.5 s after closing (with the GIL released): both interfaces at once
        def disconnect(obj) -> None:
            with contextlib.suppress(Exception):  # already broken: nothing to release
                obj.disconnect()

        workers = [threading.Thread(target=disconnect, args=(obj,), name="ur-disconnect", daemon=True)
                   for obj in (self._c, self._r) if obj is not None]
        for t in workers:
            t.start()
        for t in workers:
            t.join()
        self._c = self._r = None
        self._dash.close()

    def reconnect(self, timeout: float = 10.0) -> None:
        """Re-open every channel after a ConnectionLost (retries until ``timeout`` s)."""
        self._check_open("reconnect")
        self._drop_interfaces()
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.connect()
                return
            except (ConnectionLost, BusError) as e:
                self._drop_interfaces()
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
        lost = getattr(self, "_link_lost", False) or getattr(self, "_abandoned", None) is not None
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
        self._drop_interfaces()
        if lost:
            self._stop_program_after_link_loss()
        zombie, self._abandoned = getattr(self, "_abandoned", None), None
        if zombie is not None:
            # the control interface abandoned in a hanging call still holds its RTDE connection (and the input
            # registers the next client needs): disconnect it where a hang does no harm, waited for a moment
            def release() -> None:
                with contextlib.suppress(Exception):
                    zombie.disconnect()

            t = threading.Thread(target=release, name="ur-abandoned-disconnect", daemon=True)
            t.start()
            t.join(1.0)

    def _stop_program_after_link_loss(self) -> bool:
        """``stop`` over the dashboard (a fresh connection each try) until it answers or TEARDOWN_S passed; the
        control script ends with it, and a later connect uploads a fresh one. False (and a warning) if not."""
        deadline = time.monotonic() + self.TEARDOWN_S
        why: Exception | None = None
        while True:
            dash = DashboardClient(self.host, timeout=0.5)
            try:
                reply = dash.stop_program()
                log.info("ur://%s: program stopped over the dashboard after the link loss (%s)", self.host, reply)
                return True
            except (ConnectionLost, BusError) as e:
                why = e
            finally:
                dash.close()
            if time.monotonic() > deadline:
                break
            time.sleep(0.1)
        log.warning("ur://%s: could not stop the robot program after the link loss: the controller stayed "
                    "unreachable for %g s (%s); it may still run: press Stop on the teach pendant before "
                    "approaching the arm", self.host, self.TEARDOWN_S, why)
        return False

    # ---- link and safety checks --------------------------------------------------------------
    def _check_link(self) -> None:
        # the control interface is opened with the first motion (None before); once abandoned or lost, the link
        # is lost until a reconnect
        if self._r is None or getattr(self, "_link_lost", False):
            self._link_lost = True
            raise ConnectionLost(f"ur://{self.host}: not connected to the controller; check the network, then "
                                 "resume the session")
        if not self._r.isConnected() or (self._c is not None and not self._c.isConnected()):
            self._link_lost = True
            raise ConnectionLost(f"ur://{self.host}: connection to the controller lost (RTDE port 30004 closed); "
                                 "resume the session when the network is back")

    def _check_link_moving(self) -> None:
        """During motion: on a lost RTDE link still try to stop the program over the dashboard (it may be a
        different failure than the network), then raise."""
        try:
            self._check_link()
        except ConnectionLost:
            with contextlib.suppress(ConnectionLost, BusError):
                self._dash.stop_program()
            raise

    def _safety_error(self, bits: int) -> SafetyStop | None:
        if bits & SS_ESTOP_MASK:
            return SafetyStop(f"ur://{self.host}: emergency stop (safety_status_bits 0x{bits:x}); release the "
                              "e-stop, power on and restart")
        if bits & SS_PROTECTIVE:
            return SafetyStop(f"ur://{self.host}: protective stop (safety_status_bits 0x{bits:x}): the robot halted. "
                              "Inspect the cause, unlock it on the teach pendant (allowed 5 s after "
                              "the stop), then resume the session")
        if bits & SS_SAFEGUARD:
            return SafetyStop(f"ur://{self.host}: safeguard stop (safety_status_bits 0x{bits:x}); close the guard")
        if bits & (SS_VIOLATION | SS_FAULT):
            return SafetyStop(f"ur://{self.host}: safety system fault/violation (safety_status_bits 0x{bits:x})")
        return None

    def _check_safety(self) -> None:
        err = self._safety_error(int(self._r.getSafetyStatusBits()))
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
        """``fn(*args)`` (a ur_rtde command that waits for the controller's acknowledgement) in a worker thread,
        waited for at most the RTDE stall timeout: ur_rtde releases the GIL but never gives up on a link that
        vanished (it retries its reconnect for minutes). On expiry the worker is abandoned with its control
        interface, a stop is sent over the dashboard in the background, and ConnectionLost is raised. The wait
        wakes every 20 ms, so Ctrl-C is acted on at once."""
        box: dict = {}
        done = threading.Event()

        def run() -> None:
            try:
                box["value"] = fn(*args)
            except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
                box["error"] = e
            finally:
                done.set()

        threading.Thread(target=run, name=f"ur-{what}", daemon=True).start()
        silence = Silence()  # this process's own scheduling gaps are not the controller's silence
        while True:
            try:
                if done.wait(0.02):
                    break
            except KeyboardInterrupt:  # the command may still reach the controller later: never let it run
                self._abandon_control()
                raise
            if silence.tick() > self.stale_timeout:
                self._abandon_control()
                raise ConnectionLost(f"ur://{self.host}: the controller did not acknowledge {what} within "
                                     f"{self.stale_timeout * 1e3:.0f} ms (RTDE stall timeout; {silence.note()}): "
                                     "link lost, nothing more was sent and a stop went out over the dashboard; "
                                     "reconnect the robot when the network is back")
        if "error" in box:
            raise box["error"]
        return box["value"]

    def _abandon_control(self) -> None:
        """The control interface hangs in a call: drop it (its worker thread is left to ur_rtde) so every later
        call fails fast with ConnectionLost, and stop the program over the dashboard without waiting for it."""
        if self._c is not None:
            self._c, self._abandoned = None, self._c  # kept referenced: destroying it would block on the link
        self._speeding = False
        self._link_lost = True

        def stop() -> None:
            with contextlib.suppress(Exception):
                DashboardClient(self.host, timeout=1.0).stop_program()

        threading.Thread(target=stop, name="ur-dashboard-stop", daemon=True).start()

    def _kick(self) -> None:
        # A kick writes 0 into the command register: never within a few controller cycles of a speed
        # command, or the script would not have read the command yet (and the jog would never start).
        now = time.monotonic()
        if self._watchdog_armed and now - self._rt_sent > 0.01 and now - self._last_kick > 0.02:
            self._c.kickWatchdog()
            self._last_kick = self._last_write = now

    def _disarm_watchdog(self, keep_relaxed: bool = True) -> None:
        """Before anything that is not followed by kicks (freedrive, unwatched moves): end the script that
        carries the jog watchdog; a fresh one (without it) is uploaded by _ready_for_motion."""
        # the relaxed watchdog a waited move leaves (100 s) is kept: ending and re-uploading the script before
        # every unwatched move was a control-script start timeout on a busy PC
        if self._watchdog_armed and not (keep_relaxed and self._watchdog_hz == MOVE_IDLE_WATCHDOG_HZ):
            self._check_link()
            if self._c.isProgramRunning():
                self._c.stopScript()
            self._watchdog_hz = 0.0

    def _mode_name(self, mode: int | None = None) -> str:
        if mode is None:
            mode = int(self._r.getRobotMode()) if self._r is not None else -1
        return ROBOT_MODES.get(mode, str(mode))

    def _power_up(self) -> None:
        """Bring the arm to RUNNING the way UR's ROS driver does (robot_state_helper): ``power on``, wait for
        IDLE (joints booted, brakes engaged), ``brake release``, wait for RUNNING. Only with ``power_on=yes``;
        otherwise one line naming the option and the dashboard's robot mode. Waits count only observed time."""
        mode = int(self._r.getRobotMode())
        if mode == ROBOT_MODE_RUNNING:
            return
        self._check_safety()
        if not self.power_on:
            raise ConfigError(f"ur://{self.host}: the arm is not running (dashboard: "
                              f"{self._dash.command('robotmode')}); power it on and release the brakes on the teach "
                              "pendant, or let the station do it: add power_on=yes to the robot URL")
        if mode in (ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, 2):  # 2: BOOTING
            if mode == ROBOT_MODE_POWER_OFF:
                log.info("ur://%s: power on (power_on=yes)", self.host)
                self._dash.command("power on")
            mode = self._wait_mode((ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING), POWER_ON_TIMEOUT_S, "power-on",
                                   "IDLE after 'power on'")
        if mode == ROBOT_MODE_IDLE:
            log.info("ur://%s: brake release (power_on=yes)", self.host)
            self._dash.command("brake release")
            mode = self._wait_mode((ROBOT_MODE_RUNNING,), BRAKE_RELEASE_TIMEOUT_S, "brake-release",
                                   "RUNNING after 'brake release'")
        if mode != ROBOT_MODE_RUNNING:
            raise DeviceFault(f"ur://{self.host}: the arm is in robot mode {self._mode_name(mode)}, which needs the "
                              "teach pendant (confirm safety, release the teach button); nothing was moved")

    def _wait_mode(self, targets: tuple[int, ...], timeout: float, which: str, what: str) -> int:
        silence = Silence()  # the station's own scheduling gaps are not the controller's slowness
        while True:
            self._check_link()
            mode = int(self._r.getRobotMode())
            if mode in targets:
                return mode
            bits = int(self._r.getSafetyStatusBits())
            err = self._safety_error(bits)
            if err is not None:
                raise err
            if silence.tick() > timeout:
                raise DeviceFault(f"ur://{self.host}: {which} timeout: the arm did not reach {what} within "
                                  f"{timeout:g} s (robot mode {self._mode_name(mode)}; {silence.note()})")
            time.sleep(0.02)

    def _open_control(self) -> None:
        """ur_rtde's RTDEControlInterface, without its own wait for the control script (``FLAG_NO_WAIT``, no
        upload by the constructor): the driver uploads the script and waits for it itself (``_start_script``),
        counting only time it observed. Its constructor's wait counts 10 ms sleeps up to 5 s."""
        flags = rtde_control.RTDEControlInterface.Flags.FLAG_NO_WAIT
        deadline = time.monotonic() + 2.0
        while True:
            try:
                self._c = rtde_control.RTDEControlInterface(self.host, -1.0, flags)
                return
            except Exception as e:  # noqa: BLE001 - ur_rtde raises RuntimeError
                # a previous client's connection may still be closing (its registers are freed when its socket
                # closes): give it a moment before calling the robot taken
                if "already in use" in str(e) and time.monotonic() < deadline:
                    time.sleep(0.2)
                    continue
                if "already in use" in str(e):
                    raise BusError(f"ur://{self.host}: another RTDE client already controls this robot (input "
                                   "registers in use); close it, or disable EtherNet/IP, PROFINET and MODBUS units "
                                   "on the controller") from None
                raise ConnectionLost(f"ur://{self.host}: RTDE control (script upload on 30003) failed: {e}") \
                    from None

    def _start_script(self) -> None:
        """Upload ur_rtde's control script (a stale one is stopped first) and wait until the controller runs it:
        CONTROL_SCRIPT_TIMEOUT_S of observed time (``Silence``: a busy station PC's own gaps do not count)."""
        self._watchdog_hz = 0.0  # a new script has no watchdog
        log.info("ur://%s: starting the control script", self.host)
        self._c.reuploadScript()
        silence = Silence()
        while not self._c.isProgramRunning():
            self._check_link()
            if silence.tick() > CONTROL_SCRIPT_TIMEOUT_S:
                raise DeviceFault(f"ur://{self.host}: control-script start timeout: the controller did not run "
                                  f"ur_rtde's control script within {CONTROL_SCRIPT_TIMEOUT_S:g} s (runtime_state "
                                  f"{self._r.getRuntimeState()}, robot mode {self._mode_name()}; {silence.note()}); "
                                  "is the arm RUNNING, in remote control, and no program of the pendant running?")
            time.sleep(0.01)

    def _ready_for_motion(self) -> None:
        self._check_link()
        self._check_safety()
        if int(self._r.getRobotMode()) != ROBOT_MODE_RUNNING:
            self._power_up()
        if self._c is None:
            self._open_control()
            self._start_script()
            return
        self._kick()
        if not self._c.isProgramRunning():
            # after an unlock, a dashboard stop or a watchdog stop, the control script must run again
            log.info("ur://%s: control script not running: re-uploading", self.host)
            self._start_script()

    def _refused(self, what: str) -> None:
        """A ur_rtde command returned False: say why, leave the robot stopped."""
        self._check_link()
        bits = int(self._r.getSafetyStatusBits())
        err = self._safety_error(bits)
        # a field diagnosis: the controller ends the program when its RTDE watchdog starves (PolyScope's log
        # says so; RTDE does not), so say whether one was armed and how long ago we last wrote
        watchdog = (f"; its RTDE watchdog ({self._watchdog_hz:g} Hz) was armed, last write "
                    f"{(time.monotonic() - self._last_write) * 1e3:.0f} ms before" if self._watchdog_armed else "")
        self._halt_quietly()
        if err is not None:
            raise err
        raise DeviceFault(f"ur://{self.host}: {what} was not executed by the controller (runtime_state "
                          f"{self._r.getRuntimeState()}, robot_mode {self._r.getRobotMode()}){watchdog}")

    @property
    def _watchdog_armed(self) -> bool:
        return self._watchdog_hz > 0

    def _arm_watchdog(self, hz: float) -> None:
        """The script's rtde_set_watchdog on the command register at ``hz`` (``"stop"``: a station or network
        that stops writing stops the program); it stays armed until the script ends. No-op when already at hz."""
        if hz <= 0 or self._watchdog_hz == hz:
            return
        if self._bounded("setWatchdog", self._c.setWatchdog, hz):
            self._watchdog_hz = hz
            self._last_write = time.monotonic()
        # refused: the script is gone (a new one starts without a watchdog: _ready_for_motion). What it carried
        # and our last write are kept, so the next command can tell whether that watchdog ended it.

    def _watchdog_ended_script(self, previous_write: float) -> bool:
        """The script is gone and the jog watchdog can be what ended it: armed, and nothing written for at least
        its period (the controller counts from receiving our write, which is later than sending it). Anything
        else that ends the script (Stop on the pendant, a script error) is never resumed by the driver."""
        return (not self._c.isProgramRunning() and self._watchdog_armed
                and time.monotonic() - previous_write >= 1.0 / self._watchdog_hz)

    def _restart_after_watchdog(self, what: str, previous_write: float) -> None:
        """A station starved of CPU for a whole watchdog period (a loaded PC) had the arm stopped by the
        controller: say so, then a fresh script (a safety stop found meanwhile is raised instead)."""
        log.warning("ur://%s: the RTDE watchdog (%g Hz) ended the control script %.0f ms after our last write "
                    "(this process was not scheduled); %s on a fresh script", self.host, self._watchdog_hz,
                    (time.monotonic() - previous_write) * 1e3, what)
        self._why_script_stopped()
        self._watchdog_hz = 0.0
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
        self._check_link()
        silence = Silence()  # a loaded station PC's own gaps are not counted against the stream
        ts_entry = self._r.getTimestamp()
        while True:
            ts1 = self._r.getTimestamp()
            q = self._r.getActualQ()
            ts2 = self._r.getTimestamp()
            if ts1 == ts2 and ts1 != ts_entry:
                break
            if silence.tick() > self.stale_timeout:
                self._check_link()
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
        self._check_link()
        return np.asarray(self._r.getActualTCPPose(), dtype=float)

    def move_joints(self, q, speed: float | None = None, wait: bool = True) -> None:
        target = self._checked_target(q, "move_joints")
        v = self._checked_speed(speed, "move_joints", "rad/s", float(self.model.max_velocity.min())) or self.speed
        if not wait:
            self._disarm_watchdog()  # nobody kicks while an unwatched move runs
        self._interrupt.clear()
        self._ready_for_motion()
        self._move(target, v, wait)

    def _move(self, target: np.ndarray, v: float, wait: bool, watch: bool = True) -> None:
        start = self.joint_positions().q
        watch = wait and watch and self.move_watchdog > 0
        if watch:  # ur_rtde's script runs a moveJ to its end without a client: the watchdog stops a dead station's
            self._arm_watchdog(self.move_watchdog)
        previous = self._last_write
        ok = self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True)
        self._last_write = time.monotonic()
        if not ok and self._watchdog_ended_script(previous):
            # between the check before this move and the move (seen on a loaded CI host)
            self._restart_after_watchdog("moveJ is sent again", previous)
            ok = self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True)
            self._last_write = time.monotonic()
        if not ok:
            self._refused("moveJ")
        if wait:
            lead = float(np.max(np.abs(target - start)))
            self._wait_move(target, lead / v + 2 * v / self.accel + 5.0, v if watch else None)
            if watch and self._watchdog_armed:  # standing, nothing kicks until the next command: relaxed, not
                self._arm_watchdog(MOVE_IDLE_WATCHDOG_HZ)  # ended (a script start per move is slow on a busy PC)

    def _resend_after_watchdog(self, target: np.ndarray, v: float) -> None:
        """The move watchdog ended the script because this process did not kick it for a whole period (a loaded
        PC): a fresh script, the move watchdog again, and the same moveJ from where the arm stopped."""
        self._restart_after_watchdog("the move is finished", self._last_write)
        self._arm_watchdog(self.move_watchdog)
        if not self._bounded("moveJ", self._c.moveJ, target.tolist(), v, self.accel, True):
            self._refused("moveJ")
        self._last_write = time.monotonic()

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
            self._disarm_watchdog()
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
            self._check_link_moving()
            self._check_safety()
            if not self._c.isProgramRunning():
                if resend_v is not None and self._watchdog_ended_script(self._last_write):
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
        self._arm_watchdog(self.jog_watchdog)
        self._speeding = True
        previous = self._last_write
        ok = send()
        self._rt_sent = self._last_write = time.monotonic()  # kicks wait for the script to read the command
        if not ok and self._watchdog_ended_script(previous):
            self._restart_after_watchdog("the speed command is sent again", previous)
            self._arm_watchdog(self.jog_watchdog)
            ok = send()
            self._rt_sent = self._last_write = time.monotonic()
        if not ok:
            self._speeding = False
            self._refused("speed command")

    def _watchdog_to_idle(self) -> None:
        """After a velocity jog's speedStop: the arm stands, so the armed watchdog may wait longer
        (JOG_IDLE_WATCHDOG_HZ) for the keep-alive until the next jog sets ``jog_watchdog`` again before its
        first speed command. At 10 Hz a keep-alive late by 0.1 s (a busy station PC) ended the program, and
        the next press had to upload the script first (or met the program ending under its speed command)."""
        if self._watchdog_armed and self._watchdog_hz > JOG_IDLE_WATCHDOG_HZ:
            self._arm_watchdog(JOG_IDLE_WATCHDOG_HZ)

    def jog_keep_alive(self) -> None:
        """Between velocity jogs: feed the jog watchdog (armed for the control script's lifetime) while no
        speed command runs, so the controller does not end the program a watchdog period after each stop.
        The arm stands still (speedStop was sent); if this process dies the watchdog ends an idle program."""
        if self._watchdog_armed and not self._speeding:
            self._check_link()
            self._kick()

    def _velocity_jog(self, send, remaining, v: float, a: float) -> None:
        total = remaining(self.joint_positions().q)
        deadline = time.monotonic() + total / v + v / a + 1.0  # the jog watchdog
        self._speeding = True
        try:
            # if this process or the network dies mid-jog, the controller stops the program itself
            # (the script's rtde_set_watchdog(..., "stop")); it stays armed until the program ends
            self._send_speed(send)
            while True:
                self._check_link_moving()
                snap = self.joint_positions()
                self._check_safety()
                if remaining(snap.q) <= v * v / (2 * a) + v * 0.004:
                    break
                if not self._c.isProgramRunning():
                    if not self._watchdog_ended_script(self._last_write):
                        self._why_script_stopped()  # a safety stop says so; else a stop nobody here asked for
                        self._speeding = False
                        raise DeviceFault(f"ur://{self.host}: the control script stopped during the jog (not by "
                                          "the station); the arm holds where it stopped")
                    # this process was kept from kicking the watchdog for a whole period: the arm stands, and the
                    # step is finished with its move
                    self._restart_after_watchdog("the step is finished with a move", self._last_write)
                    break
                if time.monotonic() > deadline:
                    raise BusError(f"ur://{self.host}: jog watchdog: the step did not complete in time; stopped")
                self._kick()
                time.sleep(0.002)
        finally:
            if self._speeding:
                self._speeding = False
                try:
                    if self._bounded("speedStop", self._c.speedStop, a * 4):
                        self._last_write = time.monotonic()
                    # the arm stands: relax the armed 10 Hz watchdog, or a late first kick of the fix move that
                    # follows a step ends the script under it (moveJ refused, runtime_state STOPPED: seen in CI)
                    self._watchdog_to_idle()
                except Exception:
                    self._halt_quietly()

    def stop(self) -> None:
        self._interrupt.set()
        self._check_link()
        try:
            if self._r.getSafetyStatusBits() & (SS_PROTECTIVE | SS_ESTOP_MASK | SS_SAFEGUARD):
                return  # already halted by the safety system; commands would be refused
            if self._c is not None and self._c.isProgramRunning():
                if self._speeding:
                    if self._bounded("speedStop", self._c.speedStop, 10.0):
                        self._last_write = time.monotonic()
                    self._speeding = False
                    self._watchdog_to_idle()
                self._bounded("stopJ", self._c.stopJ, 2.0, False)
            elif any(abs(v) > 1e-4 for v in self._r.getActualQd()):
                self._dash.stop_program()
        except (ConnectionLost, BusError):
            raise
        except Exception as e:
            self._halt_quietly()
            raise DeviceFault(f"ur://{self.host}: stop: {e}") from None

    def enable(self) -> None:
        """The arm RUNNING (powered on and brakes released: only with ``power_on=yes``, see ``_power_up``) and the
        control script running."""
        self._check_link()
        self._ready_for_motion()

    def disable(self) -> None:
        self.stop()
        self._dash.power_off()

    def status(self) -> RobotStatus:
        self._check_link()
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
        self._check_link()
        return bool((int(self._r.getActualDigitalInputBits()) >> self.contact_bit) & 1)

    def set_compliant(self, on: bool) -> None:
        """Freedrive (falls back to teach mode) so the tip can settle in a socket; off keeps the position."""
        if not on and self._compliant_mode is None:  # nothing to end; a safety stop is still said (teardown)
            self._check_link()
            self._check_safety()
            return
        if on:
            self._disarm_watchdog(keep_relaxed=False)  # the arm rests in freedrive without kicks, for any time
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
