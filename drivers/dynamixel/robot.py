"""``DynamixelRobot``: the Robot protocol over a Dynamixel Protocol 2.0 bus (one servo per joint).

URL: ``dynamixel:///dev/ttyUSB0?baud=1000000&ids=11-14&model=omx[&contact=200][&serial=SN][&fast=1]
[&retries=3][&latency=16]`` (options: ``DynamixelRobot.options``). Ids map to the model's joints in order.
Joint snapshot = one (Fast) Sync Read of Present Position; goals = one Sync Write of Profile Acceleration +
Profile Velocity + Goal Position. Ticks <-> SI through each joint's encoder scaling in the kinematic model."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time

import numpy as np
from station.drivers.dynamixel import table as T
from station.drivers.dynamixel.bus import DxlBus, unpack

from station.kinematics import Model, load_model
from station.robot.base import CHAIN_OPTIONS, RobotBase
from station.robot.errors import (
    BusError,
    ConfigError,
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

LATENCY_MS = 50.0  # default latency term: a dead servo is reported after (1 + retries) x ~102 ms ~= 0.4 s


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
        Option("fast", flag(), True, "`1`: Fast Sync Read snapshots, `0`: plain Sync Read"),
        Option("retries", integer(0, 100), 3, "retries after a COMM_RX_TIMEOUT / corrupt answer, per transaction"),
        Option("latency", number(0, 1000, unit="ms"), LATENCY_MS,
               "the latency term of the SDK's answer timeout (`bytes x byte time + 2 x latency + 2 ms`, ~102 ms "
               "per attempt by default): 50 keeps a loaded station PC's scheduling delays from counting as lost "
               "answers; `1` with the adapter's latency timer at 1 ms detects a dead servo sooner",
               default_doc="50"),
        *CHAIN_OPTIONS,
    )

    def __init__(self, port: str, *, ids: list[int], model: Model | str = "omx", baud: int = 1_000_000,
                 contact_id: int | None = None, serial: str | None = None, fast: bool = True, retries: int = 3,
                 latency_ms: float = 50.0, servo: str | int | None = None, url: str = "") -> None:
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
        self.servo = self._expected_servo(servo)
        self.bus = DxlBus(port, baud, retries, latency_ms)
        self._wd_clear = False  # every servo's bus watchdog known to be 0 (not armed, not tripped)
        self._maybe_moving = True  # a move not waited for (or cut short) may still run
        self._current_limits: dict[int, int] | None = None  # Current Limit (38, EEPROM): read once
        # Present Position (ticks) read while the arm rests holding under torque with nothing commanded since
        # (end of a waited move, torque on): the next move starts from it instead of reading again
        self._rest: list[int] | None = None
        self._interrupt = threading.Event()  # set by stop() from any thread: ends a waited move
        try:
            self.devices = self._probe()
        except BaseException:
            self._closed = True  # nothing was commanded: release the port without a stop on a silent bus
            self.bus.close()
            raise
        try:  # compliance left over from a run that died while seating: the servos say so, not our flag
            modes, _ = self._read_all(T.OPERATING_MODE, 1, False)
            self._compliant = any(m == T.MODE_CURRENT_POSITION for m in modes)
        except BaseException:
            self._closed = True
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
                "latency_ms": o["latency"], "servo": o["servo"], "url": url.raw}
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
            fw, _ = self.bus.read(i, T.FIRMWARE_VERSION, 1)
            devices.append({"id": i, "joint": self.model.joints[self.ids.index(i)].name, "model_number": number,
                            "model": T.SERVO_MODELS[number], "firmware": fw})
        if self.contact_id is not None:
            number, _ = self.bus.ping(self.contact_id)
            if number != T.CONTACT_SENSOR_MODEL:
                raise IdentityMismatch(f"dynamixel: id {self.contact_id} has model number {number}, not the contact "
                                  f"sensor ({T.CONTACT_SENSOR_MODEL})")
            fw, _ = self.bus.read(self.contact_id, T.FIRMWARE_VERSION, 1)
            devices.append({"id": self.contact_id, "joint": None, "model_number": number,
                            "model": "contact sensor", "firmware": fw})
        return devices

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

    # ---- Robot protocol ------------------------------------------------------------------------------
    def identity(self) -> Identity:
        fws = sorted({str(d["firmware"]) for d in self.devices if d["joint"] is not None})
        return Identity(vendor="ROBOTIS", model=self.model.name, serial=self.serial, firmware=",".join(fws),
                        serial_source="url" if self._serial_from_url else "derived",
                        devices=tuple(dict(d) for d in self.devices), url=self.url)

    def joint_positions(self) -> JointSnapshot:
        ticks, errors = self._guard(self._read_all, T.PRESENT_POSITION, 4)
        t = time.time()
        self._check_alerts(errors, ticks)
        q = np.array([float(self._enc(j).to_si(k)) for j, k in enumerate(ticks)])
        return JointSnapshot(q=q, raw=tuple(ticks), raw_unit="tick", t=t)

    def _profiles(self, q0: np.ndarray, q1: np.ndarray, speed: float | None) -> tuple[list[int], list[int]]:
        """Per-joint profile velocity/acceleration so all joints arrive together (straight joint path)."""
        dq = np.abs(q1 - q0)
        lead = float(dq.max())
        vmax = self.model.max_velocity
        amax = np.array([j.max_acceleration for j in self.model.joints])
        v = 0.5 * float(vmax.min()) if speed is None else float(speed)
        if lead <= 0:
            return [1] * len(self.ids), [1] * len(self.ids)
        frac = dq / lead
        scale = min(1.0, *(vmax[k] / (v * frac[k]) for k in range(len(dq)) if frac[k] > 0))
        a = float(min(amax[k] / frac[k] for k in range(len(dq)) if frac[k] > 0))
        vel, acc = [], []
        for k in range(len(dq)):
            g = self._enc(k).gear
            vel.append(max(1, math.floor(v * scale * frac[k] * g / T.VELOCITY_UNIT)) if frac[k] > 0 else 1)
            acc.append(max(1, math.floor(a * frac[k] * g / T.ACCEL_UNIT)) if frac[k] > 0 else 1)
        return vel, acc

    def move_joints(self, q: np.ndarray, speed: float | None = None, wait: bool = True) -> None:
        target = self._checked_target(q, "move")
        speed = self._checked_speed(speed, "move")
        self._check_stiff("move")
        self._interrupt.clear()
        # the start only scales the joints' profile velocities so they arrive together (each stays within
        # its limit whatever the start): a resting position read since the last command is good for it
        rest, self._rest = self._rest, None
        if rest is None:
            start_q = self.joint_positions().q
        else:
            start_q = np.array([float(self._enc(j).to_si(k)) for j, k in enumerate(rest)])
        vel, acc = self._profiles(start_q, target, speed)
        goals = [int(round(float(self._enc(j).to_counts(target[j])))) for j in range(len(self.ids))]
        payload = {i: b"".join(int(x).to_bytes(4, "little", signed=True) for x in (acc[k], vel[k], goals[k]))
                   for k, i in enumerate(self.ids)}
        if not wait:
            self._maybe_moving = True
            self._rest = None
            self._send_goals(payload, goals)
            return
        # while we watch the move, the servos' bus watchdog stops them if the bus goes quiet. A tripped
        # watchdog only re-arms from 0: the 0 is written first unless the last move (or enable()) left every
        # watchdog at 0
        if not self._wd_clear:
            self._guard(self.bus.sync_write, T.BUS_WATCHDOG, 1, {i: 0 for i in self.ids})
        self._wd_clear = False
        self._guard(self.bus.sync_write, T.BUS_WATCHDOG, 1, {i: T.WATCHDOG_UNITS for i in self.ids})
        done = False
        self._maybe_moving = True
        try:
            self._guard(self.bus.sync_write, T.PROFILE_ACCELERATION, 12, payload)
            lead_k = int(np.argmax(np.abs(target - start_q)))
            lead = float(abs(target[lead_k] - start_q[lead_k]))
            v = vel[lead_k] * T.VELOCITY_UNIT / self._enc(lead_k).gear
            a = acc[lead_k] * T.ACCEL_UNIT / self._enc(lead_k).gear
            expected = lead / v + v / a if lead > 0 else 0.0  # trapezoid (an upper bound for a triangle)
            self._wait(goals, timeout=3.0 * lead / v + 2.0, expected=expected)
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
            if first:
                first = False
                refused = [i for i, b, g in zip(self.ids, back, goals, strict=True) if b != g]
                if refused:
                    self._halt_quietly(present)
                    raise DeviceFault(f"move: {', '.join(self._name(i) for i in refused)} refused the goal "
                                      "position (outside its min/max position limits 52/48, or bus watchdog "
                                      "tripped); stopped", device=f"dynamixel:{refused[0]}")
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

    def _confirm(self, torque: bool, mode: int | None = None, current: dict[int, int] | None = None) -> None:
        """Read back what was sync-written (no status packets): torque, bus watchdog 0 and Goal Current from
        one read of 64..103, the operating mode (EEPROM, 11) from a second one if it was switched."""
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
        if current is not None:
            k = T.GOAL_CURRENT - T.TORQUE_ENABLE
            off = [i for i in self.ids if unpack(data[i][k:k + 2]) != current[i]]
            if off:
                raise DeviceFault(f"goal current not taken by {', '.join(self._name(i) for i in off)}",
                                  device=f"dynamixel:{off[0]}")
        if mode is not None:
            modes, _ = self._guard(self._read_all, T.OPERATING_MODE, 1, False)
            if any(m != mode for m in modes):
                raise DeviceFault(f"set_compliant: operating mode {mode} not accepted (read back {modes})",
                                  device="dynamixel")
        if torque and mode != T.MODE_CURRENT_POSITION:  # torque on sets goal := present: it holds there
            k = T.PRESENT_POSITION - T.TORQUE_ENABLE
            self._rest = [unpack(data[i][k:k + 4]) for i in self.ids]

    def disable(self) -> None:
        self._torque(False)

    def status(self) -> RobotStatus:
        head, _ = self._read_all(T.TORQUE_ENABLE, 7, False)  # 64..70: torque ... hardware error status
        moving, _ = self._read_all(T.MOVING, 1, False)
        watchdog, _ = self._read_all(T.BUS_WATCHDOG, 1, False)
        modes, _ = self._read_all(T.OPERATING_MODE, 1, False)
        self._compliant = any(m == T.MODE_CURRENT_POSITION for m in modes)  # the servos' word (crash leftovers)
        torque = [(h >> 0) & 0xFF for h in head]
        hw = [(h >> 48) & 0xFF for h in head]
        joints, faults = [], []
        for k, i in enumerate(self.ids):
            fault = None
            if hw[k]:
                fault = f"hardware error 0x{hw[k]:02X} ({T.describe_hardware_error(hw[k])})"
                faults.append(f"{self._name(i)}: {fault}")
            elif watchdog[k] == 255:
                fault = "bus watchdog tripped (the bus went quiet during a move): it holds; enable() clears it"
                faults.append(f"{self._name(i)}: {fault}")
            joints.append(JointState(self.model.joints[k].name, bool(torque[k]), bool(moving[k]), fault))
        return RobotStatus(enabled=all(torque), moving=any(moving), faults=tuple(faults),
                           compliant=self._compliant, joints=tuple(joints))

    def touch(self) -> bool | None:
        if self.contact_id is None:
            return None
        value, _ = self._guard(self.bus.read, self.contact_id, T.CONTACT, 1)
        return bool(value)

    def set_compliant(self, on: bool) -> None:
        """On: current-based position mode (5) with a low Goal Current, so the tip can be seated in a
        socket by hand / by the cone; off: position mode (3) holding where the arm settled. Operating
        mode is EEPROM: torque goes off for the switch (the arm is briefly unpowered)."""
        no_current = [d["id"] for d in self.devices if d["joint"] and d["model_number"] not in T.CURRENT_CAPABLE]
        if no_current:
            raise ConfigError(f"set_compliant: {', '.join(self._name(i) for i in no_current)} has no "
                              "current-based position mode (XL430 has no current sensing)")
        if self._maybe_moving:
            self.stop()  # a move not waited for may still run: hold before the torque goes off
        mode = T.MODE_CURRENT_POSITION if on else T.MODE_POSITION
        if on:
            current = {i: T.COMPLIANT_GOAL_CURRENT for i in self.ids}
        else:
            if self._current_limits is None:
                limits, _ = self._guard(self._read_all, T.CURRENT_LIMIT, 2, False)
                self._current_limits = dict(zip(self.ids, limits, strict=True))
            current = dict(self._current_limits)
        # four sync writes, confirmed once at the end: a lost torque-off makes the servo refuse the mode
        # (EEPROM), a lost mode / current / torque-on write shows in the read-back; either raises DeviceFault
        self._guard(self.bus.sync_write, T.TORQUE_ENABLE, 1, {i: 0 for i in self.ids})
        self._guard(self.bus.sync_write, T.OPERATING_MODE, 1, {i: mode for i in self.ids})
        self._guard(self.bus.sync_write, T.GOAL_CURRENT, 2, current)
        self._guard(self.bus.sync_write, T.TORQUE_ENABLE, 1, {i: 1 for i in self.ids})  # goal := present: holds
        self._confirm(torque=True, mode=mode, current=current)
        self._compliant = bool(on)

    def _offset_si(self, j: int, ticks: int) -> float:
        e = self._enc(j)
        return float(e.to_si(ticks + e.zero) - e.to_si(e.zero))

    def read_calibration(self) -> dict[str, float]:
        """``{"offset.jN": rad}``: the Homing Offset (20) each servo adds to its reading, in SI."""
        ticks, _ = self._guard(self._read_all, T.HOMING_OFFSET, 4)
        return {f"offset.j{j + 1}": self._offset_si(j, t) for j, t in enumerate(ticks)}

    def write_calibration(self, values: dict[str, float]) -> None:
        """Store absolute Homing Offsets (EEPROM): torque off, write, read back and verify, restore torque."""
        n = len(self.ids)
        ticks: dict[int, int] = {}
        for name, value in values.items():
            if not (name.startswith("offset.j") and name[8:].isdigit() and 1 <= int(name[8:]) <= n):
                raise ConfigError(f"write_calibration: {name!r} is not a joint offset of this robot "
                                  f"(offset.j1..offset.j{n})")
            if not math.isfinite(float(value)):
                raise ConfigError(f"write_calibration: {name} = {value!r} is not finite")
            j = int(name[8:]) - 1
            e = self._enc(j)
            t = int(round(float(value) * e.counts_per_unit * e.gear * e.direction))
            if abs(t) > T.HOMING_OFFSET_RANGE:
                raise LimitError(f"write_calibration: {name} = {value:.6g} rad is {t} ticks, beyond the servo's "
                                 f"homing offset range +-{T.HOMING_OFFSET_RANGE}; nothing was written")
            ticks[self.ids[j]] = t
        if not ticks:
            return
        was_on, errors = self._guard(self._read_all, T.TORQUE_ENABLE, 1, False)
        self._check_alerts(errors)  # a servo in hardware error: no calibration is written (nothing was yet)
        restore = [i for i, on in zip(self.ids, was_on, strict=True) if on and i in ticks]
        done = False
        try:
            self._torque(False, list(ticks))
            for i, t in ticks.items():
                err = self._guard(self.bus.write, i, T.HOMING_OFFSET, 4, t)
                if err & 0x7F:
                    raise DeviceFault(f"write_calibration: {self._name(i)} refused homing offset {t}: "
                                      f"{T.PACKET_ERRORS.get(err & 0x7F, err)}", device=f"dynamixel:{i}", code=err)
            back, errors = self._guard(self._read_all, T.HOMING_OFFSET, 4)
            bad = [i for i, b in zip(self.ids, back, strict=True) if i in ticks and b != ticks[i]]
            if bad:
                raise DeviceFault(f"write_calibration: read-back mismatch on {', '.join(self._name(i) for i in bad)}",
                                  device=f"dynamixel:{bad[0]}")
            # a servo that latched a hardware error during the write (alert bit) took its offset (EEPROM is
            # writable with torque off) but is not fit to move: every offset is written and read back first, so
            # the device never holds half a calibration, then the fault is raised (the write-back is "failed" and
            # a resume writes and checks again after the power cycle)
            self._check_alerts(errors)
            done = True
        finally:
            if restore and done:
                self._torque(True, restore)
            elif restore:
                with contextlib.suppress(StationError):  # the original error is the one to raise
                    self._torque(True, restore)

    def reboot(self, joint: int | str) -> None:
        """Reboot one servo (clears a latched hardware error; torque comes back off: call enable())."""
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
            log.warning("dynamixel: could not leave the bus safe: servos %s (%s) are left COMPLIANT in current-"
                        "limited mode (%s); support the arm before approaching it, then resume: the next run "
                        "switches compliance off first", self.ids, ", ".join(j.name for j in self.model.joints),
                        e)
        finally:
            self.bus.close()
