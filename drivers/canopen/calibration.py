"""Joint zero offsets on CiA 402 drives: what the drive applies now, and a new zero that really takes effect.

A drive's home offset 0x607C takes effect only when a homing completes (CiA 402 0x607C; Elmo MAN-CAN402IG 9.2
"The zero position is determined after a successful homing sequence"; Parker TPDM 12.1.7.1), so writing it and
storing it changes nothing the drive reports. The station's zero correction of a joint is therefore what the
drive adds to its encoder: ``Z = 0x6064 - 0x6063`` (position actual minus position actual internal value,
Nanotec: 0x6063 "is not set to 0 following a Homing operation"). A new ``Z`` is set by homing on the current
position (mode 6, method 37, or 35 on older drives) with the home offset that makes 0x6064 read ``0x6063 + Z``
at the pose the arm holds, then proved: at the same physical pose (0x6063 unchanged) the reported position moved
by exactly the change of ``Z``. Vendors read 0x607C two ways (0x6064 = home offset at the home position:
Nanotec, KEB; CiA 402's "zero position = home position + home offset": 0x6064 = -home offset there); the first
homing tells which, and a drive of the other kind is homed again with the sign turned."""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass

from station.drivers.canopen.cia402 import (
    CW_ENABLE,
    CW_HOMING_START,
    CW_SHUTDOWN,
    ENABLED,
    FAULTED,
    HOMING_CURRENT_POSITION,
    MODE_HM,
    MODE_PP,
    SUPPORTS_HOMING,
    SW_HOMING_ATTAINED,
    SW_HOMING_ERROR,
    SW_TARGET_REACHED,
    state_of,
)

from station.robot.errors import ConfigError, DeviceFault, StationError

log = logging.getLogger("station.drivers.canopen")
READ_ATTEMPTS = 5
TOLERANCE = 1  # counts: the read-back of a still arm whose encoder reading may flip by one


@dataclass(frozen=True)
class Zero:
    """What a drive applies now: ``offset = position - internal`` (counts), at ``internal`` (encoder counts)."""

    offset: int
    internal: int
    position: int


def read_zero(bus, node_id: int) -> Zero:
    """``0x6064 - 0x6063`` by SDO, the encoder read on both sides of the position (a still arm: equal)."""
    for _ in range(READ_ATTEMPTS):
        i1 = _internal(bus, node_id)
        p = bus.read_obj(node_id, 0x6064, 0, "i32")
        i2 = _internal(bus, node_id)
        if i1 == i2:
            return Zero(p - i1, i1, p)
    mid = round((i1 + i2) / 2)
    return Zero(p - mid, mid, p)


def _internal(bus, node_id: int) -> int:
    try:
        return bus.read_obj(node_id, 0x6063, 0, "i32")
    except DeviceFault as e:
        raise ConfigError(f"canopen node {node_id} has no position actual internal value 0x6063 ({e}): the "
                          "station cannot tell the zero the drive applies from its encoder; no write-back on this "
                          "drive") from None


class ZeroSetter:
    """Sets new zero offsets ``{node: Z counts}`` on ``robot``'s drives by homing on the current position."""

    def __init__(self, robot) -> None:
        self.robot = robot
        self.bus = robot.bus

    def apply(self, plan: dict[int, int]) -> None:
        bus = self.bus
        before = {n: read_zero(bus, n) for n in plan}
        signs = self.robot.home_signs
        # every home offset first (a fault on one drive leaves the others' zero untouched: nothing homed yet)
        for n, z in plan.items():
            bus.write_obj(n, 0x607C, 0, "i32", signs.get(n, 1) * (before[n].internal + z))
        todo = [n for n in plan if before[n].offset != plan[n]]
        if not todo:
            return
        for n in todo:
            modes = bus.read_opt(n, 0x6502, 0, "u32")
            if modes is not None and not modes & SUPPORTS_HOMING:
                raise ConfigError(f"canopen node {n} has no homing mode (0x6502 = 0x{modes:08X}): its home offset "
                                  "cannot take effect; no write-back on this drive")
        with self._enabled(), self._methods(todo):
            self._home(todo)
            after = {n: read_zero(bus, n) for n in todo}
            turned = [n for n in todo if self._check(n, before[n], after[n], plan[n]) == "turned"]
            if turned:  # a drive of the other convention: 0x6064 = -0x607C at the home position
                for n in turned:
                    signs[n] = -signs.get(n, 1)
                    bus.write_obj(n, 0x607C, 0, "i32", signs[n] * (before[n].internal + plan[n]))
                self._home(turned)
                for n in turned:
                    if self._check(n, before[n], read_zero(bus, n), plan[n]) != "ok":
                        raise self._unexplained(n, before[n], read_zero(bus, n), plan[n])

    def _check(self, n: int, old: Zero, new: Zero, z: int) -> str:
        """The proof: the same physical pose (0x6063 unchanged), and the reported position moved by exactly the
        change of the zero. "turned": it moved to minus the home offset instead (the other convention)."""
        if abs(new.internal - old.internal) > TOLERANCE:
            if abs((new.internal - old.internal) - (new.position - old.position)) <= TOLERANCE:
                raise DeviceFault(f"canopen node {n}: 0x6063 moved with the homing ({old.internal} -> "
                                  f"{new.internal} counts at the same pose): this drive does not report its raw "
                                  "encoder in 0x6063; the station cannot prove its write-back", device=f"node {n}")
            raise DeviceFault(f"canopen node {n}: the joint moved during the homing (encoder {old.internal} -> "
                              f"{new.internal} counts); nothing stored", device=f"node {n}")
        if abs(new.offset - z) <= TOLERANCE:
            return "ok"
        home = self.robot.home_signs.get(n, 1) * (old.internal + z)
        if home and abs(new.position + home) <= TOLERANCE:
            return "turned"
        raise self._unexplained(n, old, new, z)

    @staticmethod
    def _unexplained(n: int, old: Zero, new: Zero, z: int) -> DeviceFault:
        if abs(new.position - old.position) <= TOLERANCE:
            return DeviceFault(f"canopen node {n}: the homing completed but the reported position did not change "
                               f"({old.position} counts, expected {old.position + z - old.offset}): the drive did "
                               "not apply its home offset; nothing stored", device=f"node {n}")
        return DeviceFault(f"canopen node {n}: after the homing the joint reads {new.position} counts at the same "
                           f"pose, expected {old.position + z - old.offset} (zero {old.offset} -> {z}); nothing "
                           "stored", device=f"node {n}")

    @contextlib.contextmanager
    def _enabled(self):
        """Homing runs in OPERATION ENABLED. Drives that are not are enabled holding where they stand (no motion:
        a current-position homing moves nothing), and shut down again afterwards."""
        robot, bus = self.robot, self.bus
        snap = bus.round()
        faulted = [n for n in robot.nodes if state_of(snap[n][0]) in FAULTED]
        if faulted:
            raise DeviceFault(f"canopen node(s) {faulted} in FAULT: clear the fault before writing a calibration",
                              device=f"node {faulted[0]}")
        off = [n for n in robot.nodes if state_of(snap[n][0]) != ENABLED]
        if off:
            log.info("canopen: drive(s) %s enabled for the homing (%s), shut down again after it", off,
                     ", ".join(sorted({state_of(snap[n][0]) for n in off})))
            for n in robot.nodes:
                bus.preset_target(n, snap[n][1])
                bus.send_rpdo2(n, MODE_PP, 0, 0)
            robot._wait_mode(MODE_PP)
            robot._enable_all(bus.round())
        try:
            yield
        finally:
            for n in off:
                with contextlib.suppress(StationError):
                    bus.send_rpdo1(n, CW_SHUTDOWN)

    @contextlib.contextmanager
    def _methods(self, nodes: list[int]):
        """0x6098 = a current-position method for the homing, the drive's own method back afterwards (it is an
        application parameter: stored with the calibration, it would make the arm controller's next homing take
        wherever the arm stands as home)."""
        bus = self.bus
        old = {n: bus.read_opt(n, 0x6098, 0, "i8") for n in nodes}
        try:
            for n in nodes:
                for k, method in enumerate(HOMING_CURRENT_POSITION):
                    try:
                        bus.write_obj(n, 0x6098, 0, "i8", method)
                        break
                    except DeviceFault:
                        if k == len(HOMING_CURRENT_POSITION) - 1:
                            raise ConfigError(f"canopen node {n} refuses homing methods 37 and 35 (current "
                                              "position): its home offset cannot take effect without moving the "
                                              "arm; no write-back on this drive") from None
            yield
        finally:
            for n, m in old.items():
                if m is not None:
                    with contextlib.suppress(StationError):
                        bus.write_obj(n, 0x6098, 0, "i8", m)

    def _home(self, nodes: list[int]) -> None:
        """Mode 6, a rising edge of controlword bit 4, wait for "homing attained" + "target reached" (bits 12, 10;
        bit 13 is a homing error), then profile position mode again holding the position in the new frame."""
        robot, bus = self.robot, self.bus
        for n in nodes:
            bus.send_rpdo2(n, MODE_HM, 0, 0)
        robot._wait(f"mode of operation {MODE_HM}", lambda s: all(s[n][2] == MODE_HM for n in nodes), 1.0)
        for n in nodes:
            bus.send_rpdo1(n, CW_ENABLE)
        bus.round()
        for n in nodes:
            bus.send_rpdo1(n, CW_ENABLE | CW_HOMING_START)
        done = SW_HOMING_ATTAINED | SW_TARGET_REACHED
        snap = robot._wait("homing on the current position",
                           lambda s: all(s[n][0] & done == done or s[n][0] & SW_HOMING_ERROR for n in nodes), 2.0)
        failed = [n for n in nodes if snap[n][0] & SW_HOMING_ERROR]
        for n in nodes:
            bus.send_rpdo1(n, CW_ENABLE)
        if failed:
            raise DeviceFault(f"canopen node(s) {failed}: homing error (statusword bit 13)", device=f"node {failed[0]}")
        snap = bus.round()
        for n in nodes:
            bus.preset_target(n, snap[n][1])
            bus.send_rpdo2(n, MODE_PP, 0, 0)
        snap = robot._wait_mode(MODE_PP)
        for n in nodes:
            bus.send_rpdo1(n, CW_ENABLE, snap[n][1])
        log.info("canopen: homed node(s) %s on the current position", nodes)
