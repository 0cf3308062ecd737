"""Dynamixel Protocol 2.0 bus emulator on a Linux pseudo-terminal, serving a simulated world.

The station opens the pty slave path with the real ``dynamixel_sdk.PortHandler`` (pyserial underneath:
termios calls work on a pty; its one modem-line ioctl, TIOCMBIS, fails with ENOTTY and pyserial ignores it).
One servo per joint of the world's model (ids in joint order) plus an optional contact-sensor device.

World wiring (all through the public World API):
- Present Position (132) = encoder counts of ``world.encoder_q()`` (model encoder scaling) + Homing Offset (20).
- Goal Position (116) -> ``world.command_joint(j, to_si(goal - homing offset), speed, accel)`` per servo
  (each servo plans its own profile); speed from Profile Velocity (112, 0 = Velocity Limit 44), acceleration
  from Profile Acceleration (108); Goal Velocity (104) in velocity mode -> ``world.command_qd``.
- Torque Enable (64) on every joint servo <-> ``world.set_enabled``; enabling sets Goal := Present (hold).
- Operating mode 5 (current-based position) with Goal Current (102) <= COMPLIANT_CURRENT on every joint
  servo (torque on) <-> ``world.set_compliant(True)``.
- Contact sensor device register 128 <- ``world.contact()``.
- Faults from ``world.faults`` (device = servo id, or None for any): "timeout" (a device does not answer
  one packet), "corrupt" (one status packet gets a flipped byte), "device_fault" (hardware error bits,
  default overload 0x20: alert bit, torque off until reboot), "disconnect" (device, or with device=None
  the whole bus, stops answering until the emulator restarts).
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
    CONTACT_SENSOR,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_INSTRUCTION,
    HW_OVERLOAD,
    VELOCITY_UNIT,
)
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


class DynamixelEmulator:
    """``DynamixelEmulator(world, ids=[11, 12, 13, 14]).start()`` -> pty path; ``.stop()``.

    ``eeprom``: ``{id: bytes}`` from a previous ``eeprom()`` to emulate a power cycle (EEPROM items such
    as the homing offset survive, RAM does not). ``return_delay`` in units of 2 us (the servo's address 9;
    the factory default is 250 = 0.5 ms, OpenManipulator setups use 0). ``wire_timing`` delays every
    answer by the time the request and the answers take on a real half-duplex line at ``baud`` (10 bits
    per byte) plus each device's return delay."""

    def __init__(self, world, ids: list[int] | None = None, *, servo: str = "xm430", baud: int = 1_000_000,
                 return_delay: int = 0, wire_timing: bool = False, contact_id: int | None = DEFAULT_CONTACT_ID,
                 eeprom: dict[int, bytes] | None = None) -> None:
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
        eeprom = eeprom or {}
        code = BAUD_TO_CODE[baud]
        self.devices: dict[int, Device] = {}
        self.joint_ids = list(ids)  # joint order; follows ID changes
        for i in ids:
            self.devices[i] = Device(dtype, i, eeprom.get(i), baud_code=code, return_delay=return_delay)
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
        self.stats: dict = {}
        self.reset_stats()
        self._sync_world()

    def _ids_from_world(self, n: int) -> list[int]:
        cfg = None
        if hasattr(self.world, "bus_config"):
            with contextlib.suppress(Exception):
                cfg = self.world.bus_config("dynamixel")
        if isinstance(cfg, dict) and cfg.get("ids"):
            return parse_id_list(cfg["ids"])
        return list(range(1, n + 1))

    def url(self, path: str | None = None) -> str:
        """The robot URL of this bus at ``path`` (default: the started pty)."""
        ids = ",".join(str(i) for i in self.joint_ids)
        extra = "" if self.contact_id is None else f"&contact={self.contact_id}"
        extra += "" if self.baud() == 1_000_000 else f"&baud={self.baud()}"
        return f"dynamixel://{path or self.path}?model={self.model.name}&ids={ids}{extra}"

    # ---- lifecycle ----------------------------------------------------------------------------
    def start(self) -> str:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo / line discipline before the client configures the port
        self.path = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="dynamixel-emulator", daemon=True)
        self._thread.start()
        return self.path

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> DynamixelEmulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

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
                with self._lock:
                    self._check_watchdogs()
                if not r:
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
    def _world_state(self) -> dict:
        q = np.asarray(self.world.encoder_q(), dtype=float)
        qd = None
        if hasattr(self.world, "encoder_qd"):
            with contextlib.suppress(Exception):
                qd = np.asarray(self.world.encoder_qd(), dtype=float)
        return {"q": q, "qd": qd, "moving": bool(self.world.is_moving())}

    def _refresh(self, dev: Device, ws: dict) -> None:
        tick = int((time.monotonic() - self._t0) * 1000) % 32768
        dev.set("realtime_tick", tick)
        if dev.type is CONTACT_SENSOR:
            c = bool(self.world.contact())
            if c and not self._last_contact:
                dev.set("contact_count", (dev.get("contact_count") + 1) & 0xFFFF)
            self._last_contact = c
            dev.set("contact", int(c))
            return
        j = self.joint_ids.index(dev.dxl_id)
        enc = self.model.joints[j].encoder
        pos = int(round(float(enc.to_counts(ws["q"][j])))) + dev.get("homing_offset")
        dev.set("present_position", pos)
        if ws["qd"] is not None:
            dev.set("present_velocity", int(round(ws["qd"][j] * enc.gear * enc.direction / VELOCITY_UNIT)))
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

    def _sync_world(self, goals_changed: bool = False, velocity_changed: bool = False) -> None:
        """Push servo outputs into the world after a packet changed registers."""
        devs = self._joint_devs()
        torque = [d.torque for d in devs]
        if torque != self._enabled:
            for j, on in enumerate(torque):
                if self._enabled is None or on != self._enabled[j]:
                    self.world.set_enabled(on, j)
            self._enabled = torque
        enabled = all(torque)
        compliant = enabled and all(d.has("goal_current") and d.get("operating_mode") == 5
                                    and abs(d.get("goal_current")) <= COMPLIANT_CURRENT for d in devs)
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
            targets = np.array([float(self.model.joints[j].encoder.to_si(d.get("goal_position")
                                                                         - d.get("homing_offset")))
                                for j, d in enumerate(devs)])
            speeds, accels = [], []
            for j, d in enumerate(devs):
                gear = self.model.joints[j].encoder.gear
                pv = d.get("profile_velocity") or d.get("velocity_limit")  # 0: as fast as the limit allows
                speeds.append(pv * VELOCITY_UNIT / gear)
                pa = d.get("profile_acceleration")  # 0: no profile, the joint's own limit
                accels.append(pa * ACCEL_UNIT / gear if pa else np.inf)
            self._targets = targets
            self._command(targets, np.array(speeds), np.array(accels))

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
                if hasattr(self.world, "fault_joint"):
                    self.world.fault_joint(self.joint_ids.index(i), bits)  # every joint halts, this one brakes
                else:
                    self.world.halt()
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
            self._refresh(dev, ws)
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
            reply = self._status(dev)
            dev.factory_reset(opt)
            return reply
        return self._status(dev, ERR_INSTRUCTION)

    def _broadcast(self, p: pk.Packet) -> list[tuple[Device, bytes]]:
        inst, prm = p.inst, p.params
        out: list[tuple[Device, bytes]] = []
        if inst == INST_PING:
            for i in sorted(self.devices):
                dev = self.devices[i]
                if self._answering(i):
                    mt = dev.type.model_number
                    out.append((dev, self._maybe_corrupt(i, self._status(
                        dev, 0, bytes([mt & 0xFF, mt >> 8, dev.get("firmware_version")])))))
            return out
        if inst in (INST_SYNC_READ, INST_FAST_SYNC_READ):
            if len(prm) < 5:
                return out
            addr, length = _u16(prm, 0), _u16(prm, 2)
            return self._read_many([(i, addr, length) for i in prm[4:]], fast=inst == INST_FAST_SYNC_READ)
        if inst in (INST_BULK_READ, INST_FAST_BULK_READ):
            if len(prm) % 5:
                return out
            req = [(prm[k], _u16(prm, k + 1), _u16(prm, k + 3)) for k in range(0, len(prm), 5)]
            return self._read_many(req, fast=inst == INST_FAST_BULK_READ)
        if inst == INST_SYNC_WRITE:
            if len(prm) < 4:
                return out
            addr, length = _u16(prm, 0), _u16(prm, 2)
            body = prm[4:]
            if length == 0 or len(body) % (length + 1):
                return out
            chunks = [(body[k], addr, body[k + 1:k + 1 + length]) for k in range(0, len(body), length + 1)]
            self._write_many(chunks)
            return out
        if inst == INST_BULK_WRITE:
            chunks, k = [], 0
            while k + 5 <= len(prm):
                i, addr, length = prm[k], _u16(prm, k + 1), _u16(prm, k + 3)
                chunks.append((i, addr, prm[k + 5:k + 5 + length]))
                k += 5 + length
            if k == len(prm):
                self._write_many(chunks)
            return out
        if inst == INST_ACTION:
            self._action(list(self.devices.values()))
            return out
        if inst == INST_REBOOT:
            for dev in list(self.devices.values()):
                self._reboot(dev)
            return out
        if inst in (INST_WRITE, INST_REG_WRITE) and len(prm) >= 3:
            self._write_many([(i, _u16(prm, 0), prm[2:]) for i in list(self.devices)], reg=inst == INST_REG_WRITE)
        return out

    def _read_many(self, req: list[tuple[int, int, int]], fast: bool) -> list[tuple[Device, bytes]]:
        """Sync/bulk read: each listed device answers in turn; a silent device ends the chain (the next
        device waits for it on a real bus). Fast variants concatenate into one status packet."""
        ids = [i for i, _, _ in req]
        self._poll_device_faults(ids)
        ws = self._world_state()
        parts: list[tuple[Device, int, bytes]] = []
        for i, addr, length in req:
            dev = self.devices.get(i)
            if dev is None or not self._answering(i):
                break
            self._refresh(dev, ws)
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
            dev.apply(items)
            names = {f.name for f, _ in items}
            if "torque_enable" in names and dev.torque and not was_on and dev.type is not CONTACT_SENSOR:
                ws = ws or self._world_state()
                self._refresh(dev, ws)
                dev.set("goal_position", dev.get("present_position"))  # hold where it is
                goals = True
            if names & {"goal_position", "profile_velocity", "profile_acceleration"}:
                goals = True
            if "goal_velocity" in names:
                velocity = True
            if "id" in names and dev.dxl_id != old_id:
                self._rekey(old_id, dev)
        if todo:
            self._sync_world(goals_changed=goals, velocity_changed=velocity)

    def _rekey(self, old: int, dev: Device) -> None:
        self.devices.pop(old, None)
        self.devices[dev.dxl_id] = dev
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
            self.world.halt()
            for dev in self._joint_devs():
                if dev.get("bus_watchdog") == 255:
                    self._refresh(dev, ws)
                    dev.set("goal_position", dev.get("present_position"))

    def _reboot(self, dev: Device) -> None:
        dev.reboot()
        if dev.dxl_id in self.joint_ids and hasattr(self.world, "clear_fault"):
            self.world.clear_fault(self.joint_ids.index(dev.dxl_id))
        self._sync_world()

