"""``DynamixelRobot``: the Robot protocol over a Dynamixel Protocol 2.0 bus (one servo per joint).

URL: ``dynamixel:///dev/ttyUSB0?baud=1000000&ids=11-14&model=omx[&contact=200][&serial=SN][&fast=1]
[&retries=3][&latency=16][&hold_torque=0.003]`` (options: ``DynamixelRobot.options``). Ids map to the model's
joints in order. Joint snapshot = one (Fast) Sync Read of Present Position; goals = one Sync Write of Profile
Acceleration + Profile Velocity + Goal Position. Ticks <-> SI through each joint's encoder scaling in the
kinematic model and each servo's own frame (Drive Mode reverse bit, Homing Offset, turn count: ``frame.py``).
What each servo is set to is read at connect and honoured, or refused in one line (docs/hardware-dynamixel.md)."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time

import numpy as np
from station.drivers.dynamixel import table as T
from station.drivers.dynamixel.adapter import latency_timer_ms, latency_warning
from station.drivers.dynamixel.bus import DxlBus, unpack
from station.drivers.dynamixel.frame import ServoFrame, describe_mode, time_profile
from station.drivers.dynamixel.writepose import Balancer, loadable, upright_guess

from station.kinematics import Model, load_model
from station.robot.base import CHAIN_OPTIONS, RobotBase
from station.robot.errors import (
    BusError,
    ConfigError,
    ConnectionLost,
    DeviceFault,
    IdentityMismatch,
    LimitError,
    SafetyStop,
    StationError,
)
from station.robot.motion import MANUAL_TOOL_SPEED_CAP
from station.robot.protocol import Identity, JointSnapshot, JointState, RobotStatus
from station.robot.url import Option, Options, RobotURL, either, flag, id_list, integer, number, text

log = logging.getLogger("station.drivers.dynamixel")
# a servo's bus watchdog that stopped a move while the station itself was quiet for at least this share of its
# period was tripped by the station's lateness, not by lost packets: the move is sent again, at most
# WATCHDOG_RESENDS times in a row
OWN_SILENCE = 0.75
WATCHDOG_RESENDS = 3


class _WatchdogTripped(Exception):
    """Inside the driver: servos ``ids`` stopped a waited move by their bus watchdog; ``quiet`` is the station's
    own longest silence (s) since the watchdog was armed, ``present`` the Present Positions then."""

    def __init__(self, ids: list[int], present: list[int], quiet: float) -> None:
        super().__init__(ids)
        self.ids, self.present, self.quiet = ids, present, quiet

LATENCY_MS = 50.0  # default latency term: a dead servo is reported after (1 + retries) x ~102 ms ~= 0.4 s
HOLD_TORQUE = 0.003  # N m: default gravity torque under which a joint may have its torque off for an EEPROM write
WRITE_DEVIATION = 2  # ticks a joint may move while one servo is written (the others hold); more: DeviceFault


class DynamixelRobot(RobotBase):
    """A serial arm of Dynamixel X-series servos. SI units at the interface (rad, rad/s, m/s)."""

    options = Options(
        Option("baud", integer(1), 1_000_000, "bus baud rate (a rate the SDK accepts: 57600, 115200, 1000000, "
               "2000000, ...)"),
        Option("ids", id_list(), None, "servo ids **in joint order** (`11-14`, `1,2,5,6`); one per joint of the "
               "model", default_doc="1..n"),
        Option("model", text(), "omx", "kinematic model name or file; its joints' `encoder` gives ticks <-> rad"),
        Option("contact", either(none=("none", ""), otherwise=integer(0, 252)), None,
               "id of the contact-sensor device; without it `touch()` returns None"),
        Option("serial", text(), None, "robot serial number for records; without it `DXL-<MODEL>-<ids>` "
               "(deterministic)", default_doc="derived"),
        Option("servo", either(*(n.lower() for n in T.SERVO_MODELS.values()), "any",
                                 otherwise=integer(0, 65535)), None,
               "servo every joint must report (name such as `XM430-W350` or model number); checked at connect",
               default_doc="from the model (`omx`: XM430-W350), else any X-series"),
        Option("fast", flag(), True, "`1`: Fast Sync Read snapshots where the servos' firmware answers one "
               "(tried at connect; else Sync Read, said once), `0`: plain Sync Read"),
        Option("retries", integer(0, 100), 3, "retries after a COMM_RX_TIMEOUT / corrupt answer, per transaction"),
        Option("latency", number(0, 1000, unit="ms"), LATENCY_MS,
               "the latency term of the SDK's answer timeout (`bytes x byte time + 2 x latency + 2 ms`, ~102 ms "
               "per attempt by default): 50 keeps a loaded station PC's scheduling delays from counting as lost "
               "answers; `1` with the adapter's latency timer at 1 ms detects a dead servo sooner",
               default_doc="50"),
        Option("hold_torque", number(0, 10, unit="N m"), HOLD_TORQUE,
               "the gravity torque (N m, from each servo's Present Current) under which a joint may have its torque "
               "off for an EEPROM write (homing offset): a DYNAMIXEL has no brake, only its gears' friction holds "
               "it. The write-back first moves the arm where every joint to be written carries less",
               default_doc="0.003"),
        *CHAIN_OPTIONS,
    )

    def __init__(self, port: str, *, ids: list[int], model: Model | str = "omx", baud: int = 1_000_000,
                 contact_id: int | None = None, serial: str | None = None, fast: bool = True, retries: int = 3,
                 latency_ms: float = 50.0, servo: str | int | None = None, url: str = "",
                 hold_torque: float = HOLD_TORQUE, sysfs_root: str = "/sys") -> None:
        self.model: Model = load_model(model) if isinstance(model, str) else model
        n = self.model.n_joints
        if len(ids) != n or len(set(ids)) != n:
            raise ConfigError(f"dynamixel: model {self.model.name} has {n} joints but ids are {ids}; "
                              "give one distinct id per joint, in joint order (e.g. ids=11-14)")
        for j in self.model.joints:
            if j.encoder is None:
                raise ConfigError(f"dynamixel: joint {j.name} of model {self.model.name} has no encoder scaling")
        self.ids = [int(i) for i in ids]
        self.contact_id = contact_id
        self.fast = fast
        self.url = url
        self.hold_torque = float(hold_torque)
        self.servo = self._expected_servo(servo)
        self.frames = [ServoFrame(j.encoder, j.lower, j.upper) for j in self.model.joints]
        # the USB adapter's latency timer (FTDI sysfs; None: unknown, e.g. a pty): said once when above 2 ms
        self.latency_timer_ms = latency_timer_ms(port, sysfs_root)
        warning = latency_warning(port, self.latency_timer_ms)
        if warning:
            log.warning(warning)
        self.bus = DxlBus(port, baud, retries, latency_ms)
        self._wd_clear = False  # every servo's bus watchdog known to be 0 (not armed, not tripped)
        self._maybe_moving = True  # a move not waited for (or cut short) may still run
        self._limits: dict[int, tuple[int, int]] | None = None  # PWM Limit (36), Current Limit (38): EEPROM
        # Present Position (ticks) read while the arm rests holding under torque with nothing commanded since
        # (end of a waited move, torque on): the next move starts from it instead of reading again
        self._rest: list[int] | None = None
        self._interrupt = threading.Event()  # set by stop() from any thread: ends a waited move
        self._balance: Balancer | None = None  # the write-back's search for a pose (write_pose)
        self._guessed = False
        try:
            self.devices = self._probe()
            self._check_fast_sync_read()
            # compliance left over from a run that died while seating: the servos say so, not our flag
            self._compliant = self._read_compliance()
        except BaseException:
            self._closed = True  # nothing was commanded: release the port without a stop on a silent bus
            self.bus.close()
            raise
        self._serial_from_url = bool(serial)
        self.serial = serial or f"DXL-{self.model.name.upper()}-" + ".".join(str(i) for i in self.ids)

    @classmethod
    def from_url(cls, url: RobotURL, **overrides) -> DynamixelRobot:
        o = cls.options.parse(url)
        if not url.path:
            raise ConfigError(f"robot URL {url.raw!r}: no serial port path (dynamixel:///dev/ttyUSB0?...)")
        model = cls.load_url_model(url, overrides.pop("model", None) or o["model"], o["tip_link"], o["base_link"])
        args = {"ids": o["ids"] or list(range(1, model.n_joints + 1)), "model": model, "baud": o["baud"],
                "contact_id": o["contact"], "serial": o["serial"], "fast": o["fast"], "retries": o["retries"],
                "latency_ms": o["latency"], "servo": o["servo"], "url": url.raw, "hold_torque": o["hold_torque"]}
        args.update(overrides)
        return cls(url.path, **args)

    # ---- helpers --------------------------------------------------------------------------------
    def _name(self, i: int) -> str:
        j = self.ids.index(i)
        return f"servo id {i} (joint {j + 1} {self.model.joints[j].name})"

    def _enc(self, j: int):
        return self.model.joints[j].encoder

    def _expected_servo(self, servo: str | int | None) -> int | None:
        """Model number every joint servo must report (None: any supported X-series)."""
        if servo is None:
            return T.MODEL_SERVOS.get(self.model.name)
        if servo == "any":
            return None
        if isinstance(servo, int):
            return servo
        return next(k for k, v in T.SERVO_MODELS.items() if v.lower() == str(servo).lower())

    # ---- connect: what every servo is set to, read and honoured (or refused) --------------------------------
    def _status_level(self, i: int) -> int:
        """Status Return Level (68) of device ``i``, which answered a ping just now. Below 1 it answers no read
        either (the e-Manual's level 0: ping only), so a silent read means 0: then it is set to 2 for this power-on
        (RAM) and said once. Level 1 is honoured: writes are sent without waiting for a status (read back)."""
        try:
            level, _ = self.bus.read(i, T.STATUS_RETURN_LEVEL, 1)
        except ConnectionLost:
            level = 0
        if level >= 1:
            self.bus.status_level[i] = level
            return level
        # whether this write gets a status depends on which level the servo applies to it (undocumented): it is
        # awaited once (a status either comes or the wait ends), never left to answer the next read
        self.bus.status_level[i] = 2
        with contextlib.suppress(ConnectionLost):
            self.bus.write(i, T.STATUS_RETURN_LEVEL, 1, 2, retry=False)
        level, _ = self.bus.read(i, T.STATUS_RETURN_LEVEL, 1)
        self.bus.status_level[i] = level
        log.warning("dynamixel: id %d had Status Return Level 0 (answers pings only): set to %d until it is "
                    "powered off (RAM)", i, level)
        return level

    def _probe(self) -> list[dict]:
        devices = []
        for i in self.ids:
            number, _ = self.bus.ping(i)
            if self.servo is not None and number != self.servo:
                want = f"{T.SERVO_MODELS.get(self.servo, 'model')} (model number {self.servo})"
                got = f"{T.SERVO_MODELS.get(number, 'unknown model')} (model number {number})"
                raise IdentityMismatch(f"dynamixel: model {self.model.name} is built from {want} servos but "
                                       f"{self._name(i)} reports {got}; nothing was moved (use the model of this "
                                       "arm, or servo=... in the URL if it really is built that way)")
            if number not in T.SERVO_MODELS:
                raise IdentityMismatch(f"dynamixel: id {i} answers with model number {number}, not a supported "
                                       f"X-series servo ({', '.join(f'{k} {v}' for k, v in T.SERVO_MODELS.items())})")
            level = self._status_level(i)
            info, _ = self.bus.read_block(i, T.INFO_ADDR, T.INFO_SIZE)  # firmware 6 .. operating mode 11
            fw, drive, mode = info[0], info[T.DRIVE_MODE - T.INFO_ADDR], info[T.OPERATING_MODE - T.INFO_ADDR]
            stored, _ = self.bus.read(i, T.HOMING_OFFSET, 4, signed=True)
            self._configure(i, drive, mode, stored)
            devices.append({"id": i, "joint": self.model.joints[self.ids.index(i)].name, "model_number": number,
                            "model": T.SERVO_MODELS[number], "firmware": fw, "drive_mode": drive,
                            "operating_mode": mode, "status_return_level": level})
        if self.contact_id is not None:
            number, _ = self.bus.ping(self.contact_id)
            if number != T.CONTACT_SENSOR_MODEL:
                raise IdentityMismatch(f"dynamixel: id {self.contact_id} has model number {number}, not the contact "
                                       f"sensor ({T.CONTACT_SENSOR_MODEL})")
            level = self._status_level(self.contact_id)
            fw, _ = self.bus.read(self.contact_id, T.FIRMWARE_VERSION, 1)
            devices.append({"id": self.contact_id, "joint": None, "model_number": number,
                            "model": "contact sensor", "firmware": fw, "status_return_level": level})
        return devices

    def _configure(self, i: int, drive: int, mode: int, stored_offset: int) -> None:
        """Honour servo ``i``'s Drive Mode (reverse: sign; time-based profile: ms) and Operating Mode, or refuse
        what the station cannot drive, before anything moves."""
        f = self.frames[self.ids.index(i)]
        if drive & T.DRIVE_SLAVE:
            raise ConfigError(f"dynamixel: {self._name(i)} is the slave of a dual joint (Drive Mode bit 1): it "
                              "follows its master's sync cable, not the bus; the station drives one servo per joint")
        if mode not in T.POSITION_MODES:
            raise ConfigError(f"dynamixel: {self._name(i)} is in operating mode {describe_mode(mode)}; the station "
                              "moves joints in position control (3, 4 or 5): set Operating Mode (11) with "
                              "DYNAMIXEL Wizard; nothing was moved")
        f.sign = -1 if drive & T.DRIVE_REVERSE else 1
        f.time_profile = bool(drive & T.DRIVE_TIME_PROFILE)
        f.mode = mode
        f.stored_offset = int(stored_offset)
        if not f.span_fits_one_turn():
            lo, hi = f.count_range()
            raise ConfigError(f"dynamixel: joint {self.model.joints[self.ids.index(i)].name} spans {hi - lo:.0f} "
                              f"ticks, more than one servo turn ({T.ONE_TURN}): after a power-on or reboot the servo "
                              "reports its position within one turn (e-Manual, Present Position) and the station "
                              "could not tell which turn the joint is in; nothing was moved")
        if mode == T.MODE_POSITION and not f.stays_in_one_turn():
            raise ConfigError(f"dynamixel: joint {self.model.joints[self.ids.index(i)].name} crosses the 0/4095 turn "
                              f"boundary of {self._name(i)}, which Position Control Mode (3) cannot (it covers one "
                              "turn): use Extended Position Control Mode (4), or a model whose encoder zero keeps the "
                              "joint inside one turn; nothing was moved")
        if f.offset != f.stored_offset:
            log.warning("dynamixel: %s holds homing offset %d, which operating mode %s ignores (beyond +-%d): its "
                        "readings do not contain it", self._name(i), f.stored_offset, describe_mode(mode),
                        T.HOMING_OFFSET_POSITION_MODE)

    def _check_fast_sync_read(self) -> None:
        """Fast Sync Read needs servo firmware that has it (ROBOTIS-GIT/dynamixel_hardware_interface issues 79 and
        83; DynamixelSDK issue 527): one is tried at connect; unanswered, the driver uses Sync Read and says so."""
        if not self.fast:
            return
        try:
            self.bus.sync_read(T.PRESENT_POSITION, 4, self.ids, fast=True)  # retried: a loaded host is no reason
        except (ConnectionLost, BusError):
            self.fast = False
            fws = sorted({str(d["firmware"]) for d in self.devices if d["joint"] is not None})
            log.warning("dynamixel: servos %s (firmware %s) did not answer a Fast Sync Read: using Sync Read",
                        self.ids, ", ".join(fws))

    def _read_limits(self) -> dict[int, tuple[int, int]]:
        """PWM Limit (36) and Current Limit (38) per servo (EEPROM: read once)."""
        if self._limits is None:
            out = self._guard(self.bus.sync_read, T.PWM_LIMIT, 4, self.ids, self.fast, True)
            self._limits = {i: (unpack(out[i][0][0:2], False), unpack(out[i][0][2:4], False)) for i in self.ids}
        return self._limits

    def _compliant_in(self, data: dict[int, bytes], base: int) -> bool:
        """From a read covering Goal PWM (100) and Goal Current (102) at ``base``: any servo output-limited."""
        limits = self._read_limits()
        for i in self.ids:
            pwm = abs(unpack(data[i][T.GOAL_PWM - base:T.GOAL_PWM - base + 2]))
            cur = abs(unpack(data[i][T.GOAL_CURRENT - base:T.GOAL_CURRENT - base + 2]))
            f = self.frames[self.ids.index(i)]
            if pwm < limits[i][0] or (f.mode == T.MODE_CURRENT_POSITION and cur < limits[i][1]):
                return True
        return False

    def _read_compliance(self) -> bool:
        out = self.bus.sync_read(T.GOAL_PWM, 4, self.ids, self.fast, True)
        return self._compliant_in({i: out[i][0] for i in self.ids}, T.GOAL_PWM)

    def _read_all(self, addr: int, size: int, signed: bool = True, retry: bool = True) -> tuple[list[int], list[int]]:
        out = self.bus.sync_read(addr, size, self.ids, self.fast, retry)
        return [unpack(out[i][0], signed) for i in self.ids], [out[i][1] for i in self.ids]

    def _halt_quietly(self, ticks: list[int] | None = None, skip: set[int] = frozenset()) -> None:
        """Best effort on a fault path: every servo still under torque holds where it is (goal := present).
        Never raises: the caller is about to raise the real error."""
        try:
            if ticks is None:
                ticks, _ = self._read_all(T.PRESENT_POSITION, 4, retry=False)
            self.bus.sync_write(T.GOAL_POSITION, 4, {i: t for i, t in zip(self.ids, ticks, strict=True)
                                                    if i not in skip})
            self._read_all(T.GOAL_POSITION, 4, retry=False)  # answered: the servos have taken the new goal
        except Exception:  # noqa: BLE001 - the bus may be gone; the original fault is what matters
            pass

    def _check_alerts(self, errors: list[int], ticks: list[int] | None = None) -> None:
        bad = [i for i, e in zip(self.ids, errors, strict=True) if e & T.ALERT]
        if not bad:
            return
        self._halt_quietly(ticks, skip=set(bad))
        parts = []
        code = 0
        for i in bad:
            try:
                bits, _ = self.bus.read(i, T.HARDWARE_ERROR_STATUS, 1)
            except BusError:
                bits = 0
            code = code or bits
            parts.append(f"{self._name(i)}: hardware error 0x{bits:02X} ({T.describe_hardware_error(bits)})")
        j = self.ids.index(bad[0])
        raise DeviceFault("; ".join(parts) + f"; its torque is off until the servo restarts: remove the cause, "
                          f"power-cycle the servos ({self.model.joints[j].name} included), then resume the session; "
                          "the other servos hold position", device=f"dynamixel:{bad[0]}", code=code)

    def _guard(self, fn, *args, **kw):
        """Run a bus operation; on a bus error, stop what can be stopped, then re-raise."""
        try:
            return fn(*args, **kw)
        except BusError:
            # a fresh reading or nothing: holding at a stale position would move the arm back
            self._halt_quietly()
            raise

    # ---- the servos' frames ---------------------------------------------------------------------------
    def _readings(self, present: list[int]) -> list[int]:
        """Present Position registers -> joint readings (ticks, model direction, calibration included)."""
        return [f.reading(p) for f, p in zip(self.frames, present, strict=True)]

    def _q(self, present: list[int]) -> np.ndarray:
        return np.array([f.to_si(r) for f, r in zip(self.frames, self._readings(present), strict=True)])

    def _physical(self, present: list[int]) -> list[int]:
        """Joint encoder counts without any homing offset (what moves when the arm moves)."""
        return [r - f.offset_ticks for f, r in zip(self.frames, self._readings(present), strict=True)]

    # ---- Robot protocol ------------------------------------------------------------------------------
    def identity(self) -> Identity:
        fws = sorted({str(d["firmware"]) for d in self.devices if d["joint"] is not None})
        return Identity(vendor="ROBOTIS", model=self.model.name, serial=self.serial, firmware=",".join(fws),
                        serial_source="url" if self._serial_from_url else "derived",
                        devices=tuple(dict(d) for d in self.devices), url=self.url)

    @property
    def adapter(self) -> dict:
        """The USB adapter as far as the station can tell: its FTDI latency timer (ms), "unknown" without one."""
        timer = self.latency_timer_ms
        return {"port": self.bus.path, "latency_timer": "unknown" if timer is None else f"{timer} ms"}

    def joint_positions(self) -> JointSnapshot:
        ticks, errors = self._guard(self._read_all, T.PRESENT_POSITION, 4)
        t = time.time()
        self._check_alerts(errors, ticks)
        readings = self._readings(ticks)
        q = np.array([f.to_si(r) for f, r in zip(self.frames, readings, strict=True)])
        return JointSnapshot(q=q, raw=tuple(readings), raw_unit="tick", t=t)

    def _profiles(self, q0: np.ndarray, q1: np.ndarray, speed: float | None
                  ) -> tuple[list[int], list[int], float]:
        """Per joint (Profile Acceleration, Profile Velocity) register values so that all joints arrive together
        (straight joint path), each in its servo's profile units (velocity-based: 214.577 rev/min^2 and 0.229
        rev/min; time-based, Drive Mode bit 2: acceleration time and move time in ms); and the move's time (s)."""
        n = len(self.ids)
        dq = np.abs(q1 - q0)
        lead = float(dq.max())
        vmax = self.model.max_velocity
        amax = np.array([j.max_acceleration for j in self.model.joints])
        v = 0.5 * float(vmax.min()) if speed is None else float(speed)
        if lead <= 0:
            return [1] * n, [1] * n, 0.0
        frac = dq / lead
        scale = min(1.0, *(vmax[k] / (v * frac[k]) for k in range(n) if frac[k] > 0))
        a = float(min(amax[k] / frac[k] for k in range(n) if frac[k] > 0))
        acc, vel = [], []
        for k in range(n):
            g = self._enc(k).gear
            vel.append(max(1, math.floor(v * scale * frac[k] * g / T.VELOCITY_UNIT)) if frac[k] > 0 else 1)
            acc.append(max(1, math.floor(a * frac[k] * g / T.ACCEL_UNIT)) if frac[k] > 0 else 1)
        lead_k = int(np.argmax(dq))
        v_lead = vel[lead_k] * T.VELOCITY_UNIT / self._enc(lead_k).gear
        a_lead = acc[lead_k] * T.ACCEL_UNIT / self._enc(lead_k).gear
        t_acc = v_lead / a_lead
        if lead >= v_lead * t_acc:
            duration = lead / v_lead + t_acc  # trapezoid
        else:
            t_acc = math.sqrt(lead / a_lead)  # triangle
            duration = 2 * t_acc
        if any(f.time_profile for f in self.frames):
            pa, pv = time_profile(duration, t_acc)
            if pv > T.PROFILE_TIME_MAX:
                raise LimitError(f"move: {duration:.1f} s is longer than a time-based profile can take "
                                 f"({T.PROFILE_TIME_MAX} ms); nothing was sent (move faster or in steps)")
            for k, f in enumerate(self.frames):
                if f.time_profile:  # every joint in the same time: they arrive together by construction
                    acc[k], vel[k] = pa, pv
            duration = pv / 1000.0
        return acc, vel, duration

    def move_joints(self, q: np.ndarray, speed: float | None = None, wait: bool = True) -> None:
        target = self._checked_target(q, "move")
        speed = self._checked_speed(speed, "move")
        self._check_stiff("move")
        self._interrupt.clear()
        # the start only scales the joints' profile velocities so they arrive together (each stays within
        # its limit whatever the start): a resting position read since the last command is good for it
        rest, self._rest = self._rest, None
        start_q = self.joint_positions().q if rest is None else self._q(rest)
        acc, vel, expected = self._profiles(start_q, target, speed)
        goals = [f.goal(f.to_reading(target[j])) for j, f in enumerate(self.frames)]
        payload = self._profile_payload(acc, vel, goals)
        if not wait:
            self._maybe_moving = True
            self._rest = None
            self._send_goals(payload, goals)
            return
        # while we watch the move, the servos' bus watchdog stops them if the bus goes quiet. A station that was
        # itself quiet that long (a loaded host: a collection, another process on the cores) finds the arm
        # stopped where it was: it says so and sends the same move again, from there, a bounded number of times
        for attempt in range(1 + WATCHDOG_RESENDS):
            try:
                self._watched_move(payload, goals, expected)
                return
            except _WatchdogTripped as trip:
                quiet = trip.quiet
                own = quiet >= OWN_SILENCE * T.WATCHDOG_UNITS * 0.02
                if not own or attempt == WATCHDOG_RESENDS:
                    self._halt_quietly(trip.present)
                    why = (f"the station was quiet on the bus for {quiet * 1e3:.0f} ms, {attempt + 1} time(s) in a "
                           "row (the host is overloaded)" if own else
                           f"although the station was never quiet for more than {quiet * 1e3:.0f} ms: packets are "
                           "being lost (check the cable, the adapter's latency timer and the termination)")
                    raise DeviceFault(f"move: the bus watchdog of {', '.join(self._name(i) for i in trip.ids)} "
                                      f"stopped the move ({T.WATCHDOG_UNITS * 20} ms without a packet) {why}; "
                                      "the servos hold", device=f"dynamixel:{trip.ids[0]}") from None
                log.warning("dynamixel: the station was quiet on the bus for %.0f ms during a move (the host is "
                            "loaded); the servos' bus watchdog stopped the arm, as it must; the same move is sent "
                            "again from where it stopped (%d of %d)", quiet * 1e3, attempt + 1, WATCHDOG_RESENDS)
                acc, vel, expected = self._profiles(self._q(trip.present), target, speed)
                payload = self._profile_payload(acc, vel, goals)

    def _profile_payload(self, acc, vel, goals: list[int]) -> dict[int, bytes]:
        """Per servo: Profile Acceleration, Profile Velocity, Goal Position (108..119), one Sync Write."""
        return {i: b"".join(int(x).to_bytes(4, "little", signed=True) for x in (acc[k], vel[k], goals[k]))
                for k, i in enumerate(self.ids)}

    def _watched_move(self, payload: dict[int, bytes], goals: list[int], expected: float) -> None:
        """The goals sent and waited for under the servos' bus watchdog: armed before the goals (a tripped
        watchdog only re-arms from 0: the 0 is written first unless the last move, or enable(), left every
        watchdog at 0) and back to 0 at the end."""
        if not self._wd_clear:
            self._guard(self.bus.sync_write, T.BUS_WATCHDOG, 1, {i: 0 for i in self.ids})
        self._wd_clear = False
        self.bus.quiet_from_now()
        self._guard(self.bus.sync_write, T.BUS_WATCHDOG, 1, {i: T.WATCHDOG_UNITS for i in self.ids})
        done = False
        self._maybe_moving = True
        try:
            self._guard(self.bus.sync_write, T.PROFILE_ACCELERATION, 12, payload)
            self._wait(goals, timeout=3.0 * expected + 2.0, expected=expected)
            done = True
        finally:
            if done:
                self._guard(self.bus.sync_write, T.BUS_WATCHDOG, 1, {i: 0 for i in self.ids})
                self._wd_clear = True  # see docs/hardware-dynamixel.md: a lost 0 shows as a refused next goal
                self._maybe_moving = False
            else:
                with contextlib.suppress(StationError):
                    self.bus.sync_write(T.BUS_WATCHDOG, 1, {i: 0 for i in self.ids})

    def _send_goals(self, payload: dict[int, bytes], goals: list[int]) -> None:
        """Sync Write has no status: read the goals back, so a refused goal (position limits 48/52, bus
        watchdog, hardware error) is caught now and the servos have taken it when this returns."""
        self._guard(self.bus.sync_write, T.PROFILE_ACCELERATION, 12, payload)
        back, errors = self._guard(self._read_all, T.GOAL_POSITION, 4)
        self._check_alerts(errors)
        refused = [i for i, b, g in zip(self.ids, back, goals, strict=True) if b != g]
        if refused:
            self._halt_quietly()
            raise DeviceFault(f"move: {', '.join(self._name(i) for i in refused)} refused the goal position "
                              "(outside its min/max position limits 52/48, or bus watchdog tripped); stopped",
                              device=f"dynamixel:{refused[0]}")

    def _wait(self, goals: list[int], timeout: float, expected: float = 0.0) -> None:
        """Poll until every servo is in position: one sync read of Goal Position .. Present Position (116..135)
        per poll. The first poll, right after the Sync Write, is its confirmation (Sync Write has no status):
        a refused goal (position limits 48/52, tripped bus watchdog, hardware error) is caught there. Polls are
        sparse while the profile still runs (``expected`` s) and every 2 ms near its end."""
        t0 = time.monotonic()
        deadline = t0 + timeout
        first = True
        while True:
            if self._interrupt.is_set():
                raise SafetyStop("move: interrupted by stop(); the arm holds where it stopped")
            out = self._guard(self.bus.sync_read, T.GOAL_POSITION, T.POLL_SIZE, self.ids, self.fast)
            data = [out[i][0] for i in self.ids]
            back = [unpack(d[0:4]) for d in data]
            present = [unpack(d[T.POLL_PRESENT:T.POLL_PRESENT + 4]) for d in data]
            self._check_alerts([out[i][1] for i in self.ids], present)
            # a goal that is not ours: refused at the first poll (position limits 48/52, a tripped bus watchdog),
            # or taken back later by the servo itself (its bus watchdog: goal := present)
            refused = [i for i, b, g in zip(self.ids, back, goals, strict=True) if b != g]
            if refused:
                if self._interrupt.is_set():  # stop() wrote the hold position: not a refusal
                    raise SafetyStop("move: interrupted by stop(); the arm holds where it stopped")
                self._raise_tripped(present)
                self._halt_quietly(present)
                raise DeviceFault(f"move: {', '.join(self._name(i) for i in refused)} "
                                  + ("refused the goal position (outside its min/max position limits 52/48); "
                                     if first else "lost its goal position during the move (another client on "
                                     "the bus?); ") + "stopped", device=f"dynamixel:{refused[0]}")
            first = False
            if not any(d[T.POLL_MOVING] for d in data) and max(
                    abs(p - g) for p, g in zip(present, goals, strict=True)) <= 10:  # the moving threshold
                self._rest = present
                return
            now = time.monotonic()
            if now > deadline:
                self._halt_quietly(present)
                raise DeviceFault(f"move: the arm did not reach its target within {timeout:.1f} s "
                                  "(blocked or torque off?); it was stopped", device="dynamixel")
            # half the expected remaining time, 2..50 ms (the bus watchdog needs a packet every 200 ms)
            time.sleep(min(0.05, max(0.002, (t0 + expected - now) / 2)))

    def _raise_tripped(self, present: list[int]) -> None:
        """Raise ``_WatchdogTripped`` if a servo's Bus Watchdog (98) reads 255 (tripped), with the station's own
        longest silence since it was armed."""
        quiet = self.bus.longest_quiet
        state, _ = self._guard(self._read_all, T.BUS_WATCHDOG, 1, False)
        tripped = [i for i, w in zip(self.ids, state, strict=True) if w == 255]
        if tripped:
            raise _WatchdogTripped(tripped, present, quiet)

    def jog(self, mode: str, axis: int, step: float, speed: float | None = None) -> None:
        snap = self.joint_positions()
        target, v = self._jog_plan(snap.q, mode, axis, step, speed, joint_default=None,
                                   tool_default=MANUAL_TOOL_SPEED_CAP)
        self.move_joints(target, v, wait=True)

    def stop(self) -> None:
        """Every servo holds where it is now (goal := present); a waited move in another thread ends."""
        self._interrupt.set()
        self._rest = None
        ticks, _ = self._read_all(T.PRESENT_POSITION, 4)
        self.bus.sync_write(T.GOAL_POSITION, 4, dict(zip(self.ids, ticks, strict=True)))
        goals, _ = self._read_all(T.GOAL_POSITION, 4)  # sync write has no status: confirm it landed
        late = [i for i, g, t in zip(self.ids, goals, ticks, strict=True) if abs(g - t) > 10]
        if not late:
            self._maybe_moving = False
        if late:
            raise DeviceFault(f"stop: {', '.join(self._name(i) for i in late)} did not take the hold position "
                              "(bus watchdog or hardware error?)", device=f"dynamixel:{late[0]}")

    def _torque(self, on: bool, ids: list[int] | None = None) -> None:
        ids = self.ids if ids is None else ids
        self._rest = None
        self._guard(self.bus.sync_write, T.TORQUE_ENABLE, 1, {i: int(on) for i in ids})
        state, errors = self._guard(self._read_all, T.TORQUE_ENABLE, 1, False)
        wrong = [i for i, s in zip(self.ids, state, strict=True) if i in ids and bool(s) != on]
        if wrong:
            self._check_alerts(errors)
            raise DeviceFault(f"torque {'on' if on else 'off'} refused by {', '.join(self._name(i) for i in wrong)}",
                              device=f"dynamixel:{wrong[0]}")

    def enable(self) -> None:
        """Torque on every servo (goal := present: it holds) and every bus watchdog cleared to 0 (one that
        tripped when a previous run lost the bus mid-move refuses goals until then), confirmed by one read."""
        self._guard(self.bus.sync_write, T.BUS_WATCHDOG, 1, {i: 0 for i in self.ids})
        self._guard(self.bus.sync_write, T.TORQUE_ENABLE, 1, {i: 1 for i in self.ids})
        self._confirm(torque=True)
        self._wd_clear = True
        self._maybe_moving = False

    def _confirm(self, torque: bool, pwm: dict[int, int] | None = None, current: dict[int, int] | None = None
                 ) -> dict[int, bytes]:
        """Read back what was sync-written (no status packets) in one read of 64..135: torque, bus watchdog 0,
        Goal PWM / Goal Current if they were written; the resting position when the torque is on."""
        self._rest = None
        out = self._guard(self.bus.sync_read, T.TORQUE_ENABLE, T.CONFIRM_SIZE, self.ids, self.fast, True)
        data = {i: out[i][0] for i in self.ids}
        errors = [out[i][1] for i in self.ids]
        wrong = [i for i in self.ids if bool(data[i][0]) != torque]
        if wrong:
            self._check_alerts(errors)
            raise DeviceFault(f"torque {'on' if torque else 'off'} refused by "
                              f"{', '.join(self._name(i) for i in wrong)}", device=f"dynamixel:{wrong[0]}")
        tripped = [i for i in self.ids if data[i][T.BUS_WATCHDOG - T.TORQUE_ENABLE] != 0]
        if tripped:
            raise DeviceFault(f"bus watchdog of {', '.join(self._name(i) for i in tripped)} did not clear "
                              "(still armed or tripped)", device=f"dynamixel:{tripped[0]}")
        for what, addr, want in (("goal PWM", T.GOAL_PWM, pwm), ("goal current", T.GOAL_CURRENT, current)):
            if want is not None:
                k = addr - T.TORQUE_ENABLE
                off = [i for i in want if unpack(data[i][k:k + 2]) != want[i]]
                if off:
                    raise DeviceFault(f"{what} not taken by {', '.join(self._name(i) for i in off)}",
                                      device=f"dynamixel:{off[0]}")
        k = T.PRESENT_POSITION - T.TORQUE_ENABLE
        present = [unpack(data[i][k:k + 4]) for i in self.ids]
        self._readings(present)  # the turn after a torque-on (Position Control Mode resets it)
        if torque and pwm is None:  # torque on sets goal := present: it holds there
            self._rest = present
        return data

    def disable(self) -> None:
        """Torque off on every servo. A DYNAMIXEL has no brake: every joint gravity loads falls (support the arm
        first)."""
        self._torque(False)

    def status(self) -> RobotStatus:
        out = self.bus.sync_read(T.TORQUE_ENABLE, T.GOAL_CURRENT + 2 - T.TORQUE_ENABLE, self.ids, self.fast, True)
        data = {i: out[i][0] for i in self.ids}
        moving, _ = self._read_all(T.MOVING, 1, False)
        self._compliant = self._compliant_in(data, T.TORQUE_ENABLE)  # the servos' word (crash leftovers)
        joints, faults = [], []
        torque = []
        for k, i in enumerate(self.ids):
            on = bool(data[i][0])
            hw = data[i][T.HARDWARE_ERROR_STATUS - T.TORQUE_ENABLE]
            watchdog = data[i][T.BUS_WATCHDOG - T.TORQUE_ENABLE]
            fault = None
            if hw:
                fault = f"hardware error 0x{hw:02X} ({T.describe_hardware_error(hw)})"
                faults.append(f"{self._name(i)}: {fault}")
            elif watchdog == 255:
                fault = "bus watchdog tripped (the bus went quiet during a move): it holds; enable() clears it"
                faults.append(f"{self._name(i)}: {fault}")
            torque.append(on)
            joints.append(JointState(self.model.joints[k].name, on, bool(moving[k]), fault))
        return RobotStatus(enabled=all(torque), moving=any(moving), faults=tuple(faults),
                           compliant=self._compliant, joints=tuple(joints))

    def touch(self) -> bool | None:
        if self.contact_id is None:
            return None
        value, _ = self._guard(self.bus.read, self.contact_id, T.CONTACT, 1)
        return bool(value)

    def set_compliant(self, on: bool) -> None:
        """On: every servo's output limited by Goal PWM (100, RAM: the limit of every position mode, e-Manual Goal
        PWM), so the tip can be seated in a socket by hand / by the cone; off: back to the PWM Limit (and a
        current-based position mode's Goal Current to the Current Limit), holding where the arm settled. No
        operating-mode switch: the torque never goes off (a DYNAMIXEL has no brake; the arm would drop).
        Confirmed by one read-back."""
        if self._maybe_moving:
            self.stop()  # a move not waited for may still run: hold before the output is limited
        limits = self._read_limits()
        pwm = {i: (T.COMPLIANT_GOAL_PWM if on else limits[i][0]) for i in self.ids}
        self._guard(self.bus.sync_write, T.GOAL_PWM, 2, pwm)
        current = None
        if not on:
            mode5 = [i for i, f in zip(self.ids, self.frames, strict=True) if f.mode == T.MODE_CURRENT_POSITION]
            if mode5:
                current = {i: limits[i][1] for i in mode5}
                self._guard(self.bus.sync_write, T.GOAL_CURRENT, 2, current)
        self._guard(self.bus.sync_write, T.TORQUE_ENABLE, 1, {i: 1 for i in self.ids})  # on already: no change
        data = self._confirm(torque=True, pwm=pwm, current=current)
        self._compliant = bool(on)
        if not on:  # it holds where it settled: the next move starts there
            k = T.PRESENT_POSITION - T.TORQUE_ENABLE
            self._rest = [unpack(data[i][k:k + 4]) for i in self.ids]

    # ---- calibration: the Homing Offset (20, EEPROM) --------------------------------------------------------
    def read_calibration(self) -> dict[str, float]:
        """``{"offset.jN": rad}``: the Homing Offset (20) each servo applies to its reading, in SI (in Position
        Control Mode one beyond +-1024 ticks is ignored by the servo: it reads as 0 here)."""
        ticks, _ = self._guard(self._read_all, T.HOMING_OFFSET, 4)
        for f, t in zip(self.frames, ticks, strict=True):
            f.stored_offset = t
        return {f"offset.j{j + 1}": f.offset_si(f.offset_ticks) for j, f in enumerate(self.frames)}

    def _offsets_to_write(self, values: dict[str, float] | None) -> dict[int, int]:
        """``{joint index: Homing Offset to store}`` for the values that change what a servo holds; checked
        against the range its operating mode applies (``LimitError``, nothing written)."""
        n = len(self.ids)
        out: dict[int, int] = {}
        for name, value in (values or {}).items():
            if not (name.startswith("offset.j") and name[8:].isdigit() and 1 <= int(name[8:]) <= n):
                raise ConfigError(f"write_calibration: {name!r} is not a joint offset of this robot "
                                  f"(offset.j1..offset.j{n})")
            if not math.isfinite(float(value)):
                raise ConfigError(f"write_calibration: {name} = {value!r} is not finite")
            j = int(name[8:]) - 1
            f = self.frames[j]
            t = f.offset_from_si(float(value))
            if abs(t) > f.offset_limit():
                raise LimitError(f"write_calibration: {name} = {value:.6g} rad is {t} ticks, beyond the +-"
                                 f"{f.offset_limit()} ticks servo {self.ids[j]} applies in operating mode "
                                 f"{describe_mode(f.mode)} (e-Manual, Homing Offset); nothing was written")
            if t != f.stored_offset:
                out[j] = t
        return out

    def _torque_units(self) -> np.ndarray:
        """N m (at the joint) per unit of each servo's Present Current / Present Load reading."""
        out = []
        for k in range(len(self.ids)):
            number = self.devices[k]["model_number"]
            torque, current = T.STALL.get(number, T.STALL[1020])
            unit = T.CURRENT_UNIT * torque / current if number in T.CURRENT_CAPABLE else T.LOAD_UNIT * torque
            out.append(unit * self._enc(k).gear)
        return np.array(out)

    def _holding_torques(self) -> np.ndarray:
        """Per joint, the torque (N m, model direction) the motor applies now: Present Current (126) through the
        servo's stall torque / current, or Present Load (0.1 % of the stall torque) without current sensing."""
        values, _ = self._guard(self._read_all, T.PRESENT_CURRENT, 2)
        sign = np.array([f.sign * self._enc(k).direction for k, f in enumerate(self.frames)])
        return sign * np.array(values, dtype=float) * self._torque_units()

    def write_pose(self, values: dict[str, float] | None = None) -> np.ndarray | None:
        """Where the arm must stand for ``write_calibration(values)`` (None: every joint, e.g. before the servos'
        power is cut): None when every servo to be written holds less than ``hold_torque`` of gravity here (or
        its torque is off already), else the next joint position (SI) to move to. Called again after each move
        (it measures there), until it answers None; the caller takes the arm there on a collision-checked path.
        The search: a first guess from the model (the links beyond each loaded joint straight up), then Newton
        steps on the measured holding torques (``writepose.py``)."""
        todo = list(range(len(self.ids))) if values is None else sorted(self._offsets_to_write(values))
        on, _ = self._guard(self._read_all, T.TORQUE_ENABLE, 1, False)
        todo = [j for j in todo if on[j]]
        snap = self.joint_positions()
        q = snap.q
        can = loadable(self.model, q)
        free = [j for j in range(len(self.ids)) if can[j]]  # the joints whose angle changes gravity's torques
        todo = [j for j in todo if can[j]]
        tau = self._holding_torques()
        loaded = [j for j in todo if abs(tau[j]) > self.hold_torque]
        if not loaded:
            self._balance, self._guessed = None, False
            return None
        if not self._guessed:
            self._guessed = True
            guess = upright_guess(self.model, q, todo, free)
            if np.max(np.abs(guess - q)) > math.radians(1.0):
                return guess
        if self._balance is None or not set(loaded) <= set(self._balance.joints):
            # the joints that carry load now (one moved into load: probe again, with it)
            joints = sorted(set(loaded) | set(self._balance.joints if self._balance else ()))
            moves = self._balance.moves if self._balance else 0
            ticks = [1.0 / (self._enc(k).counts_per_unit * self._enc(k).gear) for k in range(len(self.ids))]
            self._balance = Balancer(self.model.lower, self.model.upper, joints, free, self.hold_torque,
                                     self._torque_units(), ticks)
            self._balance.moves = moves
        try:
            return self._balance.next_pose(q, tau[self._balance.joints])
        except RuntimeError as e:
            self._balance, self._guessed = None, False
            raise DeviceFault(f"write_pose: {e}; nothing was written (support the arm, or raise hold_torque= in "
                              "the URL if its gears hold more)", device="dynamixel") from None

    def write_calibration(self, values: dict[str, float]) -> None:
        """Store absolute Homing Offsets (EEPROM: the servo takes them only with its torque off; it has no brake).
        One servo at a time while the others hold, and only where every servo to be written carries less than
        ``hold_torque`` of gravity (``write_pose`` finds such a pose; elsewhere: ``DeviceFault``, nothing written).
        Per servo: torque off, offset written, torque back on, in three packets back to back; then read back:
        the offset stored, the reading changed by exactly the offset's change (it took effect: the servo's
        Position Control Mode ignores offsets beyond +-1024) and no joint moved more than WRITE_DEVIATION ticks
        (``DeviceFault`` otherwise). A servo that latches a hardware error during the write (alert bit) still
        takes its offset: every offset is written and read back first, then the ``DeviceFault`` is raised, so the
        servos never hold half a calibration (the write-back journals ``failed``; resume writes and checks
        again)."""
        todo = self._offsets_to_write(values)
        if not todo:
            return
        data = self._confirm_state()
        errors = [data[i][1] for i in self.ids]
        self._check_alerts(errors)  # a servo in hardware error: no calibration is written (nothing was yet)
        on = {j: bool(data[self.ids[j]][0][0]) for j in todo}
        tau = self._holding_torques()
        loaded = [j for j in todo if on[j] and abs(tau[j]) > self.hold_torque]
        if loaded:
            what = ", ".join(f"{self.model.joints[j].name} {abs(tau[j]):.3g} N m" for j in loaded)
            raise DeviceFault(f"write_calibration: the homing offset is EEPROM, written only with the servo's torque "
                              f"off, and a DYNAMIXEL has no brake: gravity loads {what} here (more than "
                              f"hold_torque {self.hold_torque:g} N m), the joint would fall; move the arm to "
                              "robot.write_pose() first (the station's write-back does); nothing was written",
                              device=f"dynamixel:{self.ids[loaded[0]]}")
        self._rest = None
        alerts: list[int] = []
        for j, ho in todo.items():
            alerts += self._write_offset(j, ho, on[j])
        back, errors = self._guard(self._read_all, T.HOMING_OFFSET, 4)
        for f, t in zip(self.frames, back, strict=True):
            f.stored_offset = t
        bad = [self.ids[j] for j in todo if back[j] != todo[j]]
        if bad:
            raise DeviceFault(f"write_calibration: read-back mismatch on {', '.join(self._name(i) for i in bad)}",
                              device=f"dynamixel:{bad[0]}")
        self._check_alerts([e | (T.ALERT if i in alerts else 0) for i, e in zip(self.ids, errors, strict=True)])

    def _confirm_state(self) -> dict[int, tuple[bytes, int]]:
        """One read of 64..135 (torque .. present position) with the status error bytes."""
        return self._guard(self.bus.sync_read, T.TORQUE_ENABLE, T.CONFIRM_SIZE, self.ids, self.fast, True)

    def _write_offset(self, j: int, ho: int, torque_on: bool) -> list[int]:
        """Servo of joint ``j``: torque off, Homing Offset := ``ho``, torque on again (if it was), the others
        holding; checked by one read-back. Returns the ids that raised the alert flag meanwhile."""
        i = self.ids[j]
        f = self.frames[j]
        k = T.PRESENT_POSITION - T.TORQUE_ENABLE
        before = self._confirm_state()
        p0 = [unpack(before[x][0][k:k + 4]) for x in self.ids]
        c0 = self._physical(p0)
        err = 0
        try:
            if torque_on:  # three packets back to back: the joint is free only for one round trip
                self.bus.sync_write(T.TORQUE_ENABLE, 1, {i: 0})
            err = self.bus.write(i, T.HOMING_OFFSET, 4, ho)
        finally:
            if torque_on:
                with contextlib.suppress(StationError):  # a lost packet shows in the read-back below
                    self.bus.sync_write(T.TORQUE_ENABLE, 1, {i: 1})
        if err & 0x7F:
            raise DeviceFault(f"write_calibration: {self._name(i)} refused homing offset {ho}: "
                              f"{T.PACKET_ERRORS.get(err & 0x7F, err)}", device=f"dynamixel:{i}", code=err)
        after = self._confirm_state()
        alerts = [x for x in self.ids if after[x][1] & T.ALERT]
        if torque_on and not after[i][0][0] and i not in alerts:
            raise DeviceFault(f"write_calibration: {self._name(i)} did not take its torque back after the homing "
                              "offset write", device=f"dynamixel:{i}")
        old_reading, old_ticks = f.reading(p0[j]), f.offset_ticks
        f.stored_offset = ho
        p1 = [unpack(after[x][0][k:k + 4]) for x in self.ids]
        c1 = self._physical(p1)
        # the proof: at the same physical pose the reading changed by exactly the offset's change (a servo that
        # did not apply it shows as an unchanged reading where the offset changed by more than the tolerance)
        change = f.reading(p1[j]) - old_reading
        if abs(f.offset_ticks - old_ticks) > 2 * WRITE_DEVIATION and abs(change) <= WRITE_DEVIATION:
            raise DeviceFault(f"write_calibration: {self._name(i)} stores homing offset {ho} but its reading did "
                              f"not change by it (operating mode {describe_mode(f.mode)})", device=f"dynamixel:{i}")
        moved = [(x, abs(a - b)) for x, a, b in zip(self.ids, c0, c1, strict=True) if abs(a - b) > WRITE_DEVIATION]
        if moved:
            raise DeviceFault("write_calibration: " + ", ".join(f"{self._name(x)} moved {d} ticks" for x, d in moved)
                              + f" while servo {i} had its torque off for the homing offset write (more than "
                              f"{WRITE_DEVIATION}): the arm is not where it was; the servos hold it there",
                              device=f"dynamixel:{moved[0][0]}")
        return alerts

    def reboot(self, joint: int | str) -> None:
        """Reboot one servo (clears a latched hardware error; torque is off afterwards: call enable(); a DYNAMIXEL
        has no brake, so support a joint gravity loads)."""
        if isinstance(joint, str):
            names = [j.name for j in self.model.joints]
            if joint not in names:
                raise ConfigError(f"reboot: no joint {joint!r} (joints: {', '.join(names)})")
            k = names.index(joint)
        else:
            k = int(joint)
            if not 0 <= k < len(self.ids):
                raise ConfigError(f"reboot: joint index {joint} outside 0..{len(self.ids) - 1}")
        i = self.ids[k]
        self._rest = None
        self.bus.reboot(i)
        deadline = time.monotonic() + 2.0  # a real servo needs ~0.5 s to come back
        while True:
            try:
                self.bus.ping(i, retry=False)
                break
            except BusError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        self.bus.status_level[i] = 2  # RAM back to its defaults
        bits, _ = self.bus.read(i, T.HARDWARE_ERROR_STATUS, 1)
        if bits:
            raise DeviceFault(f"{self._name(i)} still reports hardware error 0x{bits:02X} "
                              f"({T.describe_hardware_error(bits)}) after reboot", device=f"dynamixel:{i}", code=bits)

    def _shutdown(self) -> None:
        """Every servo holds where it is (torque stays on: an arm must not drop), then the port is released. An arm
        still compliant (the teardown could not switch it back: the bus is gone) is said loudly, in one line."""
        try:
            with contextlib.suppress(StationError):  # closing a robot on a dead bus must still release the port
                self.stop()
            if self._compliant:
                self.set_compliant(False)
        except StationError as e:
            log.warning("dynamixel: could not leave the bus safe: servos %s (%s) are left COMPLIANT (output-"
                        "limited by Goal PWM) (%s); support the arm before approaching it, then resume: the next "
                        "run switches compliance off first", self.ids, ", ".join(j.name for j in self.model.joints),
                        e)
        finally:
            self.bus.close()
