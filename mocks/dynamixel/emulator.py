"""Dynamixel Protocol 2.0 bus emulator on a Linux pseudo-terminal, serving a simulated world.

The station opens the pty slave path with the real ``dynamixel_sdk.PortHandler`` (pyserial underneath:
termios calls work on a pty; its one modem-line ioctl, TIOCMBIS, fails with ENOTTY and pyserial ignores it).
One servo per joint of the world's model (ids in joint order) plus an optional contact-sensor device. Each
emulated behaviour names its ROBOTIS e-Manual source in docs/hardware-dynamixel.md (conformance table).

World wiring (all through the public World API):
- Present Position (132) = ``s * counts + 4096 k + Homing Offset`` with ``counts`` the encoder counts of
  ``world.encoder_q()`` (model encoder scaling), ``s`` = -1 with Drive Mode (10) bit 0 (reverse; the homing
  offset keeps its sign) and ``k`` the servo's turn count, reset to one turn (0..4095 before the offset) at
  power-on, reboot, a switch to Position Control Mode (3) and torque on in it. In mode 3 a homing offset beyond
  +-1024 is ignored (stored and read back, not applied).
- Goal Position (116) -> ``world.command_joint(j, to_si(s * (goal - offset - 4096 k)), speed, accel)`` per
  servo (each servo plans its own profile); Profile Velocity (112) / Acceleration (108) in 0.229 rev/min and
  214.577 rev/min^2, or with Drive Mode bit 2 (time-based profile) the move's time span and acceleration time
  in ms; 0 velocity = the Velocity Limit (44). Goal Velocity (104) in velocity mode -> ``world.command_qd``.
- Torque Enable (64) per joint servo <-> ``world.set_enabled``; a DYNAMIXEL has no brake (``world.default_brakes
  (False)`` unless the world file says ``joints.brakes``): a joint whose torque goes off falls under gravity.
  At power-on the arm rests at the world's start pose (an unpowered arm stands only where it is supported).
  Enabling sets Goal := Present (hold).
- Present Current (126; XL430: Present Load) <- ``world.joint_torque()`` through the servo's stall torque/current.
- Compliance: every joint servo torque on with Goal PWM (100) <= COMPLIANT_PWM, or in mode 5 with Goal Current
  (102) <= COMPLIANT_CURRENT <-> ``world.set_compliant(True)``.
- Contact sensor device register 128 <- ``world.contact()``.
- ``buses.dynamixel`` in the world file: ``fast_sync_read: false`` emulates firmware without Fast Sync / Fast
  Bulk Read (the instructions go unanswered), ``firmware`` the version the servos report,
  ``status_return_level`` what another tool left in RAM before the station connects.
- Faults from ``world.faults`` (device = servo id, or None for any): "timeout" (a device does not answer
  one packet), "corrupt" (one status packet gets a flipped byte), "device_fault" (hardware error bits,
  default overload 0x20: alert bit, torque off until reboot), "disconnect" (device, or with device=None
  the whole bus, stops answering until the emulator restarts).
- ``power_cycle()``: the servos' supply off and on: EEPROM kept, RAM to its defaults (torque off: unbraked
  joints fall; latched hardware errors and tripped watchdogs cleared; Present Position back to one turn).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty

import numpy as np
from station.mocks.dynamixel import packets as pk
from station.mocks.dynamixel.devices import Device, WriteRefused
from station.mocks.dynamixel.tables import (
    ACCEL_UNIT,
    BAUD_CODES,
    BAUD_TO_CODE,
    BY_NAME,
    COMPLIANT_CURRENT,
    COMPLIANT_PWM,
    CONTACT_SENSOR,
    CURRENT_UNIT,
    DRIVE_REVERSE,
    DRIVE_TIME_PROFILE,
    DRIVE_TORQUE_ON_GOAL,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_INSTRUCTION,
    HOMING_OFFSET_POSITION_MODE,
    HW_OVERLOAD,
    LOAD_UNIT,
    MODE_POSITION,
    ONE_TURN,
    VELOCITY_UNIT,
)
from station.mocks.emulator import EmulatorBase
from station.mocks.ids import parse_id_list

INST_PING, INST_READ, INST_WRITE, INST_REG_WRITE, INST_ACTION, INST_FACTORY_RESET = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
INST_REBOOT, INST_CLEAR, INST_SYNC_READ, INST_FAST_SYNC_READ = 0x08, 0x10, 0x82, 0x8A
INST_SYNC_WRITE, INST_BULK_READ, INST_BULK_WRITE, INST_FAST_BULK_READ = 0x83, 0x92, 0x93, 0x9A
INST_NAMES = {INST_PING: "ping", INST_READ: "read", INST_WRITE: "write", INST_REG_WRITE: "reg_write",
              INST_ACTION: "action", INST_FACTORY_RESET: "factory_reset", INST_REBOOT: "reboot",
              INST_CLEAR: "clear", INST_SYNC_READ: "sync_read", INST_FAST_SYNC_READ: "fast_sync_read",
              INST_SYNC_WRITE: "sync_write", INST_BULK_READ: "bulk_read", INST_BULK_WRITE: "bulk_write",
              INST_FAST_BULK_READ: "fast_bulk_read"}
DEFAULT_CONTACT_ID = 200


def _u16(b: bytes, i: int) -> int:
    return b[i] | (b[i + 1] << 8)


def _sync_write_chunks(prm: bytes) -> list[tuple[int, int, bytes]] | None:
    """SYNC WRITE parameters (address, length, then id + data per device) as (id, address, data); None when
    they do not divide into whole devices."""
    if len(prm) < 4:
        return None
    addr, length = _u16(prm, 0), _u16(prm, 2)
    body = prm[4:]
    if length == 0 or len(body) % (length + 1):
        return None
    return [(body[k], addr, body[k + 1:k + 1 + length]) for k in range(0, len(body), length + 1)]


def _bulk_write_chunks(prm: bytes) -> list[tuple[int, int, bytes]] | None:
    """BULK WRITE parameters (id, address, length, data per device) as (id, address, data); None when the last
    one is cut short."""
    chunks, k = [], 0
    while k + 5 <= len(prm):
        i, addr, length = prm[k], _u16(prm, k + 1), _u16(prm, k + 3)
        chunks.append((i, addr, prm[k + 5:k + 5 + length]))
        k += 5 + length
    return chunks if k == len(prm) else None


class DynamixelEmulator(EmulatorBase):
    """``DynamixelEmulator(world, ids=[11, 12, 13, 14]).start()`` -> the started emulator (``.path``: the pty,
    ``.url``: the robot URL); ``.stop()`` (idempotent); a context manager; ``.power_cycle()``.

    ``eeprom``: ``{id: bytes}`` from a previous ``eeprom()`` to start a new emulator after a power cycle (EEPROM
    items such as the homing offset survive, RAM does not). ``return_delay`` in units of 2 us (the servo's address
    9; the factory default is 250 = 0.5 ms, OpenManipulator setups use 0). ``wire_timing`` delays every answer by
    the time the request and the answers take on a real half-duplex line at ``baud`` (10 bits per byte) plus each
    device's return delay. ``fast_sync_read=False``: firmware without Fast Sync / Fast Bulk Read (no answer to
    them). ``firmware``: the version the servos report. ``status_return_level``: the servos' RAM value at start
    (what another tool left; a power cycle restores the default 2)."""

    def __init__(self, world, ids: list[int] | None = None, *, servo: str = "xm430", baud: int = 1_000_000,
                 return_delay: int = 0, wire_timing: bool = False, contact_id: int | None = DEFAULT_CONTACT_ID,
                 eeprom: dict[int, bytes] | None = None, fast_sync_read: bool = True, firmware: int | None = None,
                 status_return_level: int | None = None) -> None:
        self.world = world
        self.model = world.nominal
        n = self.model.n_joints
        if ids is None:
            ids = self._ids_from_world(n)
        ids = [int(i) for i in ids]
        if len(ids) != n:
            raise ValueError(f"dynamixel emulator: {len(ids)} servo ids {ids} for a {n}-joint model "
                             f"{self.model.name!r}; give one id per joint")
        if len(set(ids)) != len(ids) or any(not 0 <= i <= 252 for i in ids):
            raise ValueError(f"dynamixel emulator: servo ids must be distinct and in 0..252, got {ids}")
        if contact_id is not None and contact_id in ids:
            raise ValueError(f"dynamixel emulator: contact sensor id {contact_id} collides with a servo id")
        if baud not in BAUD_TO_CODE:
            raise ValueError(f"dynamixel emulator: baud {baud} not one of {sorted(BAUD_TO_CODE)}")
        dtype = BY_NAME.get(servo.lower())
        if dtype is None:
            raise ValueError(f"dynamixel emulator: unknown servo type {servo!r}; known: xm430, xl430")
        if firmware is not None and not 0 <= int(firmware) <= 255:
            raise ValueError(f"dynamixel emulator: firmware version {firmware} outside 0..255")
        if status_return_level is not None and int(status_return_level) not in (0, 1, 2):
            raise ValueError(f"dynamixel emulator: status return level {status_return_level} not 0, 1 or 2")
        eeprom = eeprom or {}
        code = BAUD_TO_CODE[baud]
        self.devices: dict[int, Device] = {}
        self.joint_ids = list(ids)  # joint order; follows ID changes
        self.fast_sync_read = bool(fast_sync_read)
        self.firmware = firmware
        for i in ids:
            self.devices[i] = Device(dtype, i, eeprom.get(i), baud_code=code, return_delay=return_delay)
            if firmware is not None:
                self.devices[i].set("firmware_version", int(firmware))
            if status_return_level is not None:
                self.devices[i].set("status_return_level", int(status_return_level))
        self.contact_id = contact_id
        if contact_id is not None:
            self.devices[contact_id] = Device(CONTACT_SENSOR, contact_id, eeprom.get(contact_id), baud_code=code,
                                              return_delay=return_delay)
        self.wire_timing = wire_timing
        self._silent: set[int] = set()
        self._bus_down = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self.path: str | None = None
        self._t0 = time.monotonic()
        self._targets = np.asarray(world.encoder_q(), dtype=float).copy()
        self._enabled: bool | None = None
        self._compliant: bool | None = None
        self._last_contact = False
        self._last_rx: dict[int, float] = {}  # per device: when it last received an instruction (watchdog)
        self._turn: dict[int, int] = {}  # per joint servo: k in Present = s*counts + 4096 k + offset
        self.power_cycles = 0
        # a fall being settled by an instant world on a worker (_release): answers meanwhile come from the state
        # before it, world calls wait in _pending
        self._world_idle = threading.Event()
        self._world_idle.set()
        self._pending: list = []
        self._ws_cache: dict | None = None
        self._warm_t = 0.0
        self._inline = False  # power_cycle: the caller's thread pays for the fall (the servos are off anyway)
        self._hold_after: set[int] = set()  # torque went on during a fall: hold where the fall left the joint
        self._let_go: set[int] = set()  # joints whose torque went off since power-on: they may still fall
        self.stats: dict = {}
        self.reset_stats()
        ws = self._world_state()
        for dev in self._joint_devs():
            self._reset_turn(dev, ws)  # power-on: Present Position within one turn
        # power-on with the torque off: the arm rests at the world's start pose (an unpowered arm only stands
        # where something supports it; the world has no table), held as by a brake until the servos first let
        # go of it. From then on a DYNAMIXEL has no brake: torque off = free run (e-Manual, Torque Enable)
        self._sync_world()
        if hasattr(self.world, "default_brakes"):
            self.world.default_brakes(False)

    def _ids_from_world(self, n: int) -> list[int]:
        cfg = None
        if hasattr(self.world, "bus_config"):
            with contextlib.suppress(Exception):
                cfg = self.world.bus_config("dynamixel")
        if isinstance(cfg, dict) and cfg.get("ids"):
            return parse_id_list(cfg["ids"])
        return list(range(1, n + 1))

    @property
    def url(self) -> str:
        """The robot URL of this bus (the started pty)."""
        if self.path is None:
            raise RuntimeError("dynamixel emulator: not started (start() opens the pty)")
        ids = ",".join(str(i) for i in self.joint_ids)
        extra = "" if self.contact_id is None else f"&contact={self.contact_id}"
        extra += "" if self.baud() == 1_000_000 else f"&baud={self.baud()}"
        return f"dynamixel://{self.path}?model={self.model.name}&ids={ids}{extra}"

    # ---- lifecycle ----------------------------------------------------------------------------
    def _startup(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo / line discipline before the client configures the port
        self.path = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="dynamixel-emulator", daemon=True)
        self._thread.start()

    def power_cycle(self) -> None:
        """The servos' supply off and on (the USB adapter, and so the pty, stays): EEPROM kept, RAM to its
        defaults: torque off (an unbraked joint falls), hardware errors and watchdogs cleared, Status Return Level
        2, Present Position back within one turn (e-Manual: Torque Enable, Present Position / operating mode
        note); a servo answers again at once."""
        self._world_idle.wait(30)
        with self._lock:
            self._inline = True
            for dev in self.devices.values():
                dev.reboot()
            if hasattr(self.world, "clear_fault"):
                self.world.clear_fault()
            self._last_rx.clear()
            self._last_contact = False
            ws = self._world_state()
            for dev in self._joint_devs():
                self._reset_turn(dev, ws)
            try:
                self._sync_world()
            finally:
                self._inline = False
            self.power_cycles += 1

    def _shutdown(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def eeprom(self) -> dict[int, bytes]:
        """EEPROM images by id, to start a new emulator after an emulated power cycle."""
        with self._lock:
            return {i: d.eeprom() for i, d in self.devices.items()}

    def reset_stats(self) -> None:
        with self._lock:
            self.stats = {"packets": 0, "bytes_in": 0, "bytes_out": 0, "bad_crc": 0, "by_inst": {},
                          "garbage": 0}

    def baud(self) -> int:
        dev = self.devices.get(self.joint_ids[0])
        return BAUD_CODES.get(dev.get("baud_rate"), 1_000_000) if dev else 1_000_000

    # ---- I/O loop ----------------------------------------------------------------------------
    def _run(self) -> None:
        parser = pk.StreamParser()
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self._master], [], [], 0.01)
                if not r:  # the watchdogs count silence on the bus: what is waiting in the pty is not silence
                    with self._lock:
                        self._check_watchdogs()
                        self._keep_warm()
                    continue
                data = os.read(self._master, 4096)
            except OSError:
                if self._stop.is_set():
                    return
                time.sleep(0.01)
                continue
            t_rx = time.perf_counter()
            for packet in parser.feed(data):
                with self._lock:
                    self.stats["garbage"] = parser.dropped
                    replies = self._handle(packet)
                    out = b"".join(r for _, r in replies)
                    self.stats["bytes_out"] += len(out)
                if self.wire_timing:
                    self._wait_wire(t_rx, packet, replies)
                if out:
                    with contextlib.suppress(OSError):
                        os.write(self._master, out)
            with self._lock:  # a busy bus keeps select() from timing out: the silent servos are counted here too
                self._check_watchdogs()

    def _wait_wire(self, t_rx: float, packet: pk.Packet, replies: list[tuple[Device, bytes]]) -> None:
        per_byte = 10.0 / self.baud()
        delay = len(packet.raw) * per_byte
        for dev, data in replies:  # a fast sync/bulk read is one reply: one return delay, then back-to-back
            delay += dev.get("return_delay_time") * 2e-6 + len(data) * per_byte
        deadline = t_rx + delay
        while True:
            left = deadline - time.perf_counter()
            if left <= 0:
                return
            if left > 0.002:
                time.sleep(left - 0.001)
            # spin the last millisecond: sleep() granularity would dominate sub-ms frames

    # ---- world ---------------------------------------------------------------------------------
    def _busy(self) -> bool:
        return not self._world_idle.is_set()

    def _world(self, fn, *args, **kw) -> None:
        """A world command now, or after the fall being settled (in order)."""
        if self._busy():
            self._pending.append(("call", lambda: fn(*args, **kw)))
        else:
            fn(*args, **kw)

    def _release(self, fn) -> None:
        """A world call that lets joints go or may settle joints that run free (torque on/off, a servo's shutdown).
        An instant world settles a fall at once, which can take it a second of CPU or more: while the bus runs
        that goes to a worker, so that the servos answer on time meanwhile with the state from before the fall (a
        real fall takes that long too); world calls that arrive meanwhile run after it, in order."""
        if getattr(self.world, "time_mode", "") != "instant" or self._thread is None or self._inline:
            self._world(fn)
            return
        if self._busy():
            self._pending.append(("release", fn))
            return
        self._ws_cache = self._world_state()
        self._world_idle.clear()
        entered = threading.Event()
        threading.Thread(target=self._settle, args=(fn, entered), name="dynamixel-emulator-fall", daemon=True).start()
        entered.wait(5)  # the world is the worker's from now on: whoever reads it next sees the joints let go

    def _settle(self, fn, entered: threading.Event) -> None:
        lock = getattr(self.world, "_lock", None) or contextlib.nullcontext()  # the world's own (re-entrant) lock
        with lock:
            entered.set()
            with contextlib.suppress(Exception):  # a world refusal must not kill the bus
                fn()
        with self._lock:  # the I/O thread waits: what queued up meanwhile runs now, in order
            pending, self._pending = self._pending, []
            self._ws_cache = None
            self._world_idle.set()
            if self._hold_after:  # a servo whose torque went on meanwhile holds where the fall took its joint
                ws = self._world_state()
                for i in self._hold_after:
                    dev = self.devices.get(i)
                    if dev is not None and dev.torque:
                        self._refresh(dev, ws)
                        dev.set("goal_position", dev.get("present_position"))
                self._hold_after.clear()
            for item in pending:  # in order; what comes after a fall handed to a new worker queues again behind it
                if item[0] == "call":
                    with contextlib.suppress(Exception):
                        self._world(item[1])
                elif item[0] == "release":  # a fall of its own: a worker again, never under the bus's lock
                    self._release(item[1])
                else:
                    self._sync_world(item[1], item[2], torque=item[3])

    def settled(self, timeout: float = 30.0) -> bool:
        """Wait until the world has caught up with everything the servos were told (a fall an instant world
        settles on a worker, and what queued behind it); True when it has."""
        end = time.monotonic() + timeout
        while self._world_idle.wait(max(0.0, end - time.monotonic())):
            with self._lock:  # a worker runs what queued up while it holds this lock
                if self._world_idle.is_set():
                    return True
            if time.monotonic() >= end:
                break
        return False

    def _keep_warm(self) -> None:
        """Realtime world: integrate free joints as time passes (every 20 ms), so that no read pays for a long
        unobserved fall at once (an answer late by the world's integration would look like a lost packet)."""
        now = time.monotonic()
        if getattr(self.world, "time_mode", "") == "realtime" and now - self._warm_t > 0.02 and not self._busy():
            self._warm_t = now
            self.world.encoder_q()

    def _world_state(self) -> dict:
        if self._busy() and self._ws_cache is not None:
            return {k: v for k, v in self._ws_cache.items() if k != "tau"}
        q = np.asarray(self.world.encoder_q(), dtype=float)
        qd = None
        if hasattr(self.world, "encoder_qd"):
            with contextlib.suppress(Exception):
                qd = np.asarray(self.world.encoder_qd(), dtype=float)
        return {"q": q, "qd": qd, "moving": bool(self.world.is_moving())}

    def _torque_now(self, ws: dict) -> np.ndarray | None:
        """world.joint_torque(), once per packet and only when a read covers Present Current/Load."""
        if "tau" not in ws:
            ws["tau"] = None
            if hasattr(self.world, "joint_torque") and not self._busy():
                with contextlib.suppress(Exception):
                    ws["tau"] = np.asarray(self.world.joint_torque(), dtype=float)
        return ws["tau"]

    def _refresh(self, dev: Device, ws: dict, addr: int = 0, length: int = 1 << 16) -> None:
        tick = int((time.monotonic() - self._t0) * 1000) % 32768
        dev.set("realtime_tick", tick)
        if dev.type is CONTACT_SENSOR:
            c = self._last_contact if self._busy() else bool(self.world.contact())
            if c and not self._last_contact:
                dev.set("contact_count", (dev.get("contact_count") + 1) & 0xFFFF)
            self._last_contact = c
            dev.set("contact", int(c))
            return
        j = self.joint_ids.index(dev.dxl_id)
        enc = self.model.joints[j].encoder
        s = self._sign(dev)
        pos = self._present(dev, ws)
        dev.set("present_position", pos)
        if ws["qd"] is not None:
            dev.set("present_velocity", int(round(s * ws["qd"][j] * enc.gear * enc.direction / VELOCITY_UNIT)))
        if addr < 128 and addr + length > 126:  # Present Current / Load read: the world's torque
            dev.set("present_current" if dev.has("present_current") else "present_load", self._load(dev, j, ws))
        # Moving (122): the profile is still running for this joint (the world's trajectory), not merely
        # "far from goal": a joint held off its goal (blocked, compliant) is not moving
        qd = 0.0 if ws["qd"] is None else abs(float(ws["qd"][j]))
        moving = ws["moving"] and (qd > 1e-9 or abs(dev.get("goal_position") - pos) > dev.get("moving_threshold"))
        dev.set("moving", int(moving))
        in_pos = abs(dev.get("goal_position") - pos) <= dev.get("moving_threshold")
        dev.set("moving_status", (0x01 if in_pos else 0) | (0x02 if moving else 0))
        dev.set("position_trajectory", dev.get("goal_position"))

    def _joint_devs(self) -> list[Device]:
        return [self.devices[i] for i in self.joint_ids if i in self.devices]

    # ---- the servo's position frame: direction, turn count, homing offset ---------------------------------------
    @staticmethod
    def _sign(dev: Device) -> int:
        """Drive Mode bit 0: reverse mode turns Goal / Present Position (and velocity, current) around."""
        return -1 if dev.get("drive_mode") & DRIVE_REVERSE else 1

    @staticmethod
    def _offset(dev: Device) -> int:
        """The homing offset the servo applies: Position Control Mode ignores one beyond +-1024 (e-Manual,
        Homing Offset); the stored value still reads back."""
        ho = dev.get("homing_offset")
        if dev.get("operating_mode") == MODE_POSITION and abs(ho) > HOMING_OFFSET_POSITION_MODE:
            return 0
        return ho

    def _counts(self, dev: Device, ws: dict) -> int:
        j = self.joint_ids.index(dev.dxl_id)
        return int(round(float(self.model.joints[j].encoder.to_counts(ws["q"][j]))))

    def _reset_turn(self, dev: Device, ws: dict) -> None:
        """Present Position back within one full rotation (0..4095 before the homing offset)."""
        self._turn[dev.dxl_id] = -((self._sign(dev) * self._counts(dev, ws)) // ONE_TURN)

    def _present(self, dev: Device, ws: dict) -> int:
        return (self._sign(dev) * self._counts(dev, ws) + ONE_TURN * self._turn.get(dev.dxl_id, 0)
                + self._offset(dev))

    def _goal_si(self, j: int, dev: Device) -> float:
        """The joint position (SI) Goal Position stands for in this servo's frame."""
        counts = self._sign(dev) * (dev.get("goal_position") - self._offset(dev)
                                    - ONE_TURN * self._turn.get(dev.dxl_id, 0))
        return float(self.model.joints[j].encoder.to_si(counts))

    def _load(self, dev: Device, j: int, ws: dict) -> int:
        """Present Current (2.69 mA) or, without current sensing, Present Load (0.1 % of the stall torque) of the
        torque the motor applies now (world.joint_torque at the joint, through the model's gear)."""
        if not dev.torque:
            return 0
        torque = self._torque_now(ws)
        if torque is None:
            return 0
        enc = self.model.joints[j].encoder
        tau = self._sign(dev) * enc.direction * float(torque[j]) / enc.gear  # N m at the servo's horn
        t = dev.type
        if dev.has("present_current") and t.stall_current > 0:
            value = tau * t.stall_current / t.stall_torque / CURRENT_UNIT
            lim = dev.get("current_limit")
        else:
            value = tau / t.stall_torque / LOAD_UNIT if t.stall_torque else 0.0
            lim = 1000
        return int(max(-lim, min(lim, round(value))))

    def _sync_world(self, goals_changed: bool = False, velocity_changed: bool = False,
                    torque: tuple[bool, ...] | None = None) -> None:
        """Push servo outputs into the world after a packet changed registers. While a fall is being settled the
        servos' torque states are queued as they were, each replayed in order: a servo released and taken back
        meanwhile still lets its joint go in the world (as briefly as the world's time allows)."""
        devs = self._joint_devs()
        if self._busy():
            state = tuple(d.torque for d in devs) if torque is None else tuple(torque)
            self._pending.append(("sync", goals_changed, velocity_changed, state))
            return
        torque = [d.torque for d in devs] if torque is None else list(torque)
        if torque != self._enabled:
            changed = [j for j, on in enumerate(torque) if self._enabled is None or on != self._enabled[j]]
            on = [j for j in changed if torque[j]]
            off = [j for j in changed if not torque[j]]
            first = self._enabled is None  # power-on: the arm rests where it stands
            self._enabled = torque
            if not first:
                self._let_go = (self._let_go | set(off)) - set(on)
            falling = bool(off and not first) or bool(self._let_go)

            def switch():
                if on:
                    self.world.set_enabled(True, on)
                if off:  # torque off: a DYNAMIXEL has no brake, the joint runs free (falls where gravity loads it)
                    self.world.set_enabled(False, off)
            if falling:  # the world settles free joints on every switch: possibly slow
                self._release(switch)
            else:
                switch()
            if self._busy():
                self._pending.append(("sync", goals_changed, velocity_changed, tuple(torque)))
                return
        self._sync_outputs(devs, goals_changed, velocity_changed)

    def _sync_outputs(self, devs: list[Device], goals_changed: bool, velocity_changed: bool) -> None:
        torque = [d.torque for d in devs]
        enabled = all(torque)
        compliant = enabled and all(abs(d.get("goal_pwm")) <= COMPLIANT_PWM
                                    or (d.has("goal_current") and d.get("operating_mode") == 5
                                        and abs(d.get("goal_current")) <= COMPLIANT_CURRENT) for d in devs)
        if compliant != self._compliant:
            self._compliant = compliant
            self.world.set_compliant(compliant)
        if not any(torque):
            return
        if velocity_changed and all(d.get("operating_mode") == 1 for d in devs):
            qd = np.array([d.get("goal_velocity") * VELOCITY_UNIT
                           / (self.model.joints[j].encoder.gear * self.model.joints[j].encoder.direction)
                           for j, d in enumerate(devs)])
            self.world.command_qd(qd)
            return
        if goals_changed and not compliant:
            targets = np.array([self._goal_si(j, d) for j, d in enumerate(devs)])
            q_now = np.asarray(self.world.encoder_q(), dtype=float)
            speeds, accels = [], []
            for j, d in enumerate(devs):
                gear = self.model.joints[j].encoder.gear
                v_limit = d.get("velocity_limit") * VELOCITY_UNIT / gear
                if d.get("drive_mode") & DRIVE_TIME_PROFILE:
                    v, a = self._time_profile(d, abs(targets[j] - q_now[j]), v_limit)
                else:
                    pv = d.get("profile_velocity")  # 0: as fast as the velocity limit allows
                    v = pv * VELOCITY_UNIT / gear if pv else v_limit
                    pa = d.get("profile_acceleration")  # 0: no profile, the joint's own limit
                    a = pa * ACCEL_UNIT / gear if pa else np.inf
                speeds.append(v)
                accels.append(a)
            self._targets = targets
            self._command(targets, np.array(speeds), np.array(accels))

    @staticmethod
    def _time_profile(dev: Device, distance: float, v_limit: float) -> tuple[float, float]:
        """Time-based profile (Drive Mode bit 2): Profile Velocity (112) is the time span t3 of the move and
        Profile Acceleration (108) its accelerating time t1, both in ms, t1 at most half of t3 (e-Manual, Profile
        Velocity / Profile Acceleration); 0 = infinite velocity / acceleration. Returns (speed, acceleration) of
        the trapezoid covering ``distance``, the speed within the velocity limit."""
        t3 = dev.get("profile_velocity") / 1000.0
        t1 = min(dev.get("profile_acceleration"), dev.get("profile_velocity") // 2) / 1000.0
        if t3 <= 0 or distance <= 0:
            return v_limit, np.inf
        v = distance / (t3 - t1)
        if v > v_limit:  # the servo cannot go faster than its limit: the move takes longer than asked
            return v_limit, (v_limit / t1 if t1 > 0 else np.inf)
        return v, (v / t1 if t1 > 0 else np.inf)

    def _command(self, targets: np.ndarray, speeds: np.ndarray, accels: np.ndarray) -> None:
        """Each servo plans its own profile (as the real ones do: joints arrive together only because the
        driver scales the profile velocities); a world without per-joint commands gets one synchronised move."""
        if hasattr(self.world, "command_joint"):
            for j, dev in enumerate(self._joint_devs()):
                if dev.torque:
                    self.world.command_joint(j, float(targets[j]), speed=max(float(speeds[j]), 1e-6),
                                             accel=None if np.isinf(accels[j]) else max(float(accels[j]), 1e-6))
            return
        accel = None if np.all(np.isinf(accels)) else np.where(np.isinf(accels), 1e9, np.maximum(accels, 1e-6))
        self.world.command_q(targets, speed=np.maximum(speeds, 1e-6), accel=accel)

    # ---- faults ----------------------------------------------------------------------------------
    def _take(self, kind: str, device) -> object | None:
        faults = getattr(self.world, "faults", None)
        if faults is None:
            return None
        if hasattr(faults, "take_fault"):
            return faults.take_fault(kind, device)
        return True if faults.take(kind, device) else None

    def _poll_device_faults(self, ids: list[int]) -> None:
        for i in ids:
            dev = self.devices.get(i)
            if dev is None or dev.type is CONTACT_SENSOR:
                continue
            f = self._take("device_fault", i)
            if f is not None:
                code = getattr(f, "code", None)
                bits = int(code) if code else HW_OVERLOAD
                dev.latch_hardware_error(bits)
                if hasattr(self.world, "fault_joint"):  # every joint halts, this one's torque goes off
                    j = self.joint_ids.index(i)
                    if self._enabled is not None:
                        self._enabled[j] = False  # the world disables it itself
                    self._let_go.add(j)
                    self._release(lambda j=j, bits=bits: self.world.fault_joint(j, bits))
                else:
                    self._world(self.world.halt)
                self._sync_world()

    def _device_disconnect_armed(self, dev_id: int) -> bool:
        """A disconnect armed for this device only (device=None means the whole bus, taken per packet)."""
        faults = getattr(self.world, "faults", None)
        if faults is None or not hasattr(faults, "pending"):
            return False
        return any(f.kind == "disconnect" and f.device is not None and str(f.device) == str(dev_id)
                   for f in faults.pending())

    def _answering(self, dev_id: int) -> bool:
        """False if the device is gone or a timeout fault swallows this answer."""
        if dev_id in self._silent:
            return False
        if self._device_disconnect_armed(dev_id) and self._take("disconnect", dev_id) is not None:
            self._silent.add(dev_id)
            return False
        return self._take("timeout", dev_id) is None

    def _maybe_corrupt(self, dev_id: int, data: bytes) -> bytes:
        if self._take("corrupt", dev_id) is None:
            return data
        b = bytearray(data)
        b[len(b) // 2] ^= 0x5A  # a flipped byte in the middle: the CRC no longer matches
        return bytes(b)

    # ---- instruction handling ----------------------------------------------------------------------
    def _handle(self, p: pk.Packet) -> list[tuple[Device, bytes]]:
        st = self.stats
        st["packets"] += 1
        st["bytes_in"] += len(p.raw)
        name = INST_NAMES.get(p.inst, f"0x{p.inst:02x}")
        st["by_inst"][name] = st["by_inst"].get(name, 0) + 1
        if self._bus_down:
            return []
        if self._take("disconnect", "bus") is not None:
            self._bus_down = True
            return []
        broadcast = p.dxl_id == pk.BROADCAST_ID
        now = time.monotonic()
        for i in self.devices:
            if (broadcast or i == p.dxl_id) and i not in self._silent:
                self._last_rx[i] = now
        if not p.crc_ok:
            st["bad_crc"] += 1
            dev = self.devices.get(p.dxl_id)
            if dev is not None and not broadcast and self._answering(p.dxl_id):
                return [(dev, pk.status(dev.dxl_id, ERR_CRC | dev.error_flags))]
            return []
        if p.inst in (INST_WRITE, INST_REG_WRITE, INST_SYNC_WRITE) and len(p.params) >= 2:
            faults = getattr(self.world, "faults", None)
            if faults is not None:  # world-file faults armed by a write to this address (docs/world.md)
                faults.notice(packet={"addr": _u16(p.params, 0), "inst": INST_NAMES.get(p.inst)})
        if broadcast:
            return self._broadcast(p)
        dev = self.devices.get(p.dxl_id)
        if dev is None:
            return []
        self._poll_device_faults([p.dxl_id])
        reply = self._unicast(dev, p)
        if reply is None or not self._answering(dev.dxl_id):
            return []
        return [(dev, self._maybe_corrupt(dev.dxl_id, reply))]

    def _status(self, dev: Device, error: int = 0, params: bytes = b"") -> bytes:
        return pk.status(dev.dxl_id, error | dev.error_flags, params)

    def _wants_reply(self, dev: Device, inst: int) -> bool:
        level = dev.get("status_return_level")
        if inst == INST_PING:
            return True
        if inst == INST_READ:
            return level >= 1
        return level >= 2

    def _unicast(self, dev: Device, p: pk.Packet) -> bytes | None:
        inst, prm = p.inst, p.params
        if inst == INST_PING:
            mt = dev.type.model_number
            return self._status(dev, 0, bytes([mt & 0xFF, mt >> 8, dev.get("firmware_version")]))
        if inst == INST_READ:
            if len(prm) != 4:
                return self._status(dev, ERR_DATA_LENGTH)
            ws = self._world_state()
            self._refresh(dev, ws, _u16(prm, 0), _u16(prm, 2))
            try:
                data = dev.read(_u16(prm, 0), _u16(prm, 2))
            except WriteRefused as e:
                return self._status(dev, e.code) if self._wants_reply(dev, inst) else None
            return self._status(dev, 0, data) if self._wants_reply(dev, inst) else None
        if inst in (INST_WRITE, INST_REG_WRITE):
            if len(prm) < 3:
                return self._status(dev, ERR_DATA_LENGTH)
            addr, data = _u16(prm, 0), prm[2:]
            try:
                items = dev.check_write(addr, data)
            except WriteRefused as e:
                return self._status(dev, e.code) if self._wants_reply(dev, inst) else None
            if inst == INST_REG_WRITE:
                dev.registered = (addr, bytes(data))
                dev.set("registered_instruction", 1)
            else:
                self._apply_writes([(dev, items)])
            return self._status(dev) if self._wants_reply(dev, inst) else None
        if inst == INST_ACTION:
            self._action([dev])
            return None  # the SDK does not wait for a status after ACTION
        if inst == INST_REBOOT:
            reply = self._status(dev) if self._wants_reply(dev, inst) else None
            self._reboot(dev)
            return reply
        if inst == INST_FACTORY_RESET:
            if dev.torque:
                return self._status(dev, 7)
            opt = prm[0] if prm else 0xFF
            reply = self._status(dev) if self._wants_reply(dev, inst) else None
            dev.factory_reset(opt)
            if dev.dxl_id in self.joint_ids:
                self._reset_turn(dev, self._world_state())
            return reply
        return self._status(dev, ERR_INSTRUCTION)

    def _broadcast(self, p: pk.Packet) -> list[tuple[Device, bytes]]:
        """An instruction to every device: PING and the sync/bulk reads are answered (each device in turn); a
        broadcast write, ACTION or REBOOT is answered by nobody."""
        if p.inst == INST_PING:
            return self._ping_all()
        if p.inst in (INST_SYNC_READ, INST_FAST_SYNC_READ, INST_BULK_READ, INST_FAST_BULK_READ):
            return self._broadcast_read(p.inst, p.params)
        self._broadcast_write(p.inst, p.params)
        return []

    def _ping_all(self) -> list[tuple[Device, bytes]]:
        out: list[tuple[Device, bytes]] = []
        for i in sorted(self.devices):
            dev = self.devices[i]
            if self._answering(i):
                mt = dev.type.model_number
                out.append((dev, self._maybe_corrupt(i, self._status(
                    dev, 0, bytes([mt & 0xFF, mt >> 8, dev.get("firmware_version")])))))
        return out

    def _broadcast_read(self, inst: int, prm: bytes) -> list[tuple[Device, bytes]]:
        if inst in (INST_FAST_SYNC_READ, INST_FAST_BULK_READ) and not self.fast_sync_read:
            return []  # firmware without the fast reads: an instruction it does not know, sent to all: silence
        if inst in (INST_SYNC_READ, INST_FAST_SYNC_READ):
            if len(prm) < 5:
                return []
            addr, length = _u16(prm, 0), _u16(prm, 2)
            return self._read_many([(i, addr, length) for i in prm[4:]], fast=inst == INST_FAST_SYNC_READ)
        if len(prm) % 5:
            return []
        req = [(prm[k], _u16(prm, k + 1), _u16(prm, k + 3)) for k in range(0, len(prm), 5)]
        return self._read_many(req, fast=inst == INST_FAST_BULK_READ)

    def _broadcast_write(self, inst: int, prm: bytes) -> None:
        """A malformed sync/bulk write is dropped whole (nothing written)."""
        if inst == INST_SYNC_WRITE:
            chunks = _sync_write_chunks(prm)
            if chunks is not None:
                self._write_many(chunks)
        elif inst == INST_BULK_WRITE:
            chunks = _bulk_write_chunks(prm)
            if chunks is not None:
                self._write_many(chunks)
        elif inst == INST_ACTION:
            self._action(list(self.devices.values()))
        elif inst == INST_REBOOT:
            for dev in list(self.devices.values()):
                self._reboot(dev)
        elif inst in (INST_WRITE, INST_REG_WRITE) and len(prm) >= 3:
            self._write_many([(i, _u16(prm, 0), prm[2:]) for i in list(self.devices)], reg=inst == INST_REG_WRITE)

    def _read_many(self, req: list[tuple[int, int, int]], fast: bool) -> list[tuple[Device, bytes]]:
        """Sync/bulk read: each listed device answers in turn; a silent device ends the chain (the next
        device waits for it on a real bus). Fast variants concatenate into one status packet."""
        ids = [i for i, _, _ in req]
        self._poll_device_faults(ids)
        ws = self._world_state()
        parts: list[tuple[Device, int, bytes]] = []
        for i, addr, length in req:
            dev = self.devices.get(i)
            # Status Return Level 0: the device answers PING only (a sync/bulk read is a READ instruction)
            if dev is None or not self._answering(i) or dev.get("status_return_level") < 1:
                break
            self._refresh(dev, ws, addr, length)
            try:
                data, err = dev.read(addr, length), 0
            except WriteRefused as e:
                data, err = bytes(length), e.code
            parts.append((dev, err | dev.error_flags, data))
        if not fast:
            out, hit = [], False  # at most one damaged answer per instruction: one fault, one frame
            for dev, err, data in parts:
                frame = pk.status(dev.dxl_id, err, data)
                if not hit:
                    damaged = self._maybe_corrupt(dev.dxl_id, frame)
                    hit, frame = damaged != frame, damaged
                out.append((dev, frame))
            return out
        if len(parts) < len(req):
            return []
        # FF FF FD 00 FE LEN 55 | ERR ID DATA CRC | ERR ID DATA CRC | ... (last CRC = packet CRC, no stuffing)
        length = 1 + sum(len(d) + 4 for _, _, d in parts)
        buf = bytearray(pk.HEADER + bytes([pk.BROADCAST_ID, length & 0xFF, length >> 8, pk.INST_STATUS]))
        for dev, err, data in parts:
            buf += bytes([err, dev.dxl_id]) + data
            crc = pk.crc16(buf)
            buf += bytes([crc & 0xFF, crc >> 8])
        first = parts[0][0] if parts else next(iter(self.devices.values()))
        raw = bytes(buf)
        for dev, _, _ in parts:
            damaged = self._maybe_corrupt(dev.dxl_id, raw)
            if damaged != raw:
                return [(first, damaged)]
        return [(first, raw)]

    def _write_many(self, chunks: list[tuple[int, int, bytes]], reg: bool = False) -> None:
        """Sync/bulk write: no status packets; a refused item on one device leaves the others applied."""
        self._poll_device_faults([i for i, _, _ in chunks])
        todo = []
        for i, addr, data in chunks:
            dev = self.devices.get(i)
            if dev is None or i in self._silent or self._bus_down:
                continue
            try:
                items = dev.check_write(addr, data)
            except WriteRefused:
                continue
            if reg:
                dev.registered = (addr, bytes(data))
                dev.set("registered_instruction", 1)
            else:
                todo.append((dev, items))
        self._apply_writes(todo)

    def _action(self, devs: list[Device]) -> None:
        todo = []
        for dev in devs:
            if dev.registered is None:
                continue
            addr, data = dev.registered
            dev.registered = None
            dev.set("registered_instruction", 0)
            try:
                todo.append((dev, dev.check_write(addr, data)))
            except WriteRefused:
                continue
        self._apply_writes(todo)

    def _apply_writes(self, todo: list[tuple[Device, list]]) -> None:
        goals = velocity = False
        ws = None
        for dev, items in todo:
            was_on = dev.torque
            old_id = dev.dxl_id
            old_mode = dev.get("operating_mode") if dev.has("operating_mode") else None
            old_drive = dev.get("drive_mode") if dev.has("drive_mode") else None
            dev.apply(items)
            names = {f.name for f, _ in items}
            joint = dev.type is not CONTACT_SENSOR and dev.dxl_id in self.joint_ids
            if joint and "goal_position" in names and not was_on and dev.get("drive_mode") & DRIVE_TORQUE_ON_GOAL \
                    and not dev.hardware_error:
                dev.set("torque_enable", 1)  # Drive Mode bit 3: a goal turns the torque on (firmware 45+)
            if joint and (("operating_mode" in names and dev.get("operating_mode") == MODE_POSITION != old_mode)
                          or ("drive_mode" in names and dev.get("drive_mode") != old_drive)
                          or (dev.torque and not was_on and dev.get("operating_mode") == MODE_POSITION)):
                # Present Position back within one turn: a switch to Position Control Mode, torque on in it
                # (e-Manual, operating mode note); a new direction (reverse bit) restarts the count, as assumed
                ws = ws or self._world_state()
                self._reset_turn(dev, ws)
            if joint and dev.torque and not was_on:
                if "goal_position" not in names:  # (torque on by goal update goes to that goal)
                    ws = ws or self._world_state()
                    self._refresh(dev, ws)
                    dev.set("goal_position", dev.get("present_position"))  # hold where it is
                    if self._busy():
                        self._hold_after.add(dev.dxl_id)  # where it is once the fall being settled is done
                goals = True
            if names & {"goal_position", "profile_velocity", "profile_acceleration"}:
                goals = True
            if "goal_position" in names:  # a goal written after the torque went on is the one the servo holds,
                self._hold_after.discard(dev.dxl_id)  # not where a fall still being settled leaves the joint
            if "goal_velocity" in names:
                velocity = True
            if "id" in names and dev.dxl_id != old_id:
                self._rekey(old_id, dev)
        if todo:
            self._sync_world(goals_changed=goals, velocity_changed=velocity)

    def _rekey(self, old: int, dev: Device) -> None:
        self.devices.pop(old, None)
        self.devices[dev.dxl_id] = dev
        if old in self._turn:
            self._turn[dev.dxl_id] = self._turn.pop(old)
        if old in self.joint_ids:
            self.joint_ids[self.joint_ids.index(old)] = dev.dxl_id
        if old == self.contact_id:
            self.contact_id = dev.dxl_id

    def _check_watchdogs(self) -> None:
        """Bus Watchdog (98): a servo that hears nothing for value x 20 ms stops (goal := present) and
        refuses goals (value reads 255) until 0 or a new period is written."""
        now = time.monotonic()
        tripped = False
        for i in self.joint_ids:
            dev = self.devices.get(i)
            if dev is None:
                continue
            wd = dev.get("bus_watchdog")
            if 0 < wd <= 127 and now - self._last_rx.get(i, now) > wd * 0.02:
                dev.set("bus_watchdog", 255)
                tripped = True
        if tripped:
            ws = self._world_state()
            self._world(self.world.halt)
            for dev in self._joint_devs():
                if dev.get("bus_watchdog") == 255:
                    self._refresh(dev, ws)
                    dev.set("goal_position", dev.get("present_position"))

    def _reboot(self, dev: Device) -> None:
        dev.reboot()
        if dev.dxl_id in self.joint_ids:
            self._reset_turn(dev, self._world_state())
            if hasattr(self.world, "clear_fault"):
                self._world(self.world.clear_fault, self.joint_ids.index(dev.dxl_id))
        self._sync_world()

