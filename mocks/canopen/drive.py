"""One emulated CiA 402 servo drive: a ``canopen.LocalNode`` loaded from the shipped EDS, plus the glue
LocalNode lacks (402 state machine, profile position/velocity/torque, homing, PDO engine, NMT with boot-up,
heartbeat consumer, EMCY, store/restore parameters).

Position frame (docs/hardware-canopen.md, "Position, homing and the write-back contract"): the encoder gives
``0x6063 = E`` (position actual internal value, increments; Nanotec: "not set to 0 following a Homing
operation"), ``E = round(counts(q_raw)) - origin`` where ``q_raw`` is the world's encoder position, ``counts``
the drive's own resolution (0x608F, 0x6091) and ``origin`` the count at power-up of an incremental encoder (0
for an absolute one). The drive reports ``0x6064 = E + Z`` where ``Z`` (0x2001, the homing result) is set only
when a homing completes: homing method 35/37 ("current position") makes ``0x6064`` equal to the home offset
0x607C at the present position (or to minus it: the world's ``home_offset: zero`` convention). Writing 0x607C
changes nothing until then. Targets (0x607A) are in the 0x6064 frame; the drive keeps its internal target in
raw counts, so a homing never moves the joint.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field
from fractions import Fraction
from typing import TYPE_CHECKING, Any, Protocol

import canopen
from canopen.sdo import SdoAbortedError
from station.mocks.canopen.device_control import (
    CW_FAULT_RESET,
    CW_HALT,
    CW_HOMING_START,
    CW_NEW_SETPOINT,
    CW_RELATIVE,
    FAULT,
    FRA,
    NOT_READY,
    OE,
    QSA,
    RTSO,
    SO,
    SOD,
    STATE_BITS,
    SW_HOMING_ATTAINED,
    SW_HOMING_ERROR,
    SW_LIMIT,
    SW_REMOTE,
    SW_SETPOINT_ACK,
    SW_TARGET_REACHED,
    next_state,
)
from station.mocks.canopen.eds import (
    CONTACT_INPUT_BIT,
    DEFAULT_TORQUE_LIMIT,
    EDS_PATH,
    LOAD_SIGNATURE,
    POSITION_OFFSET,
    SAVE_SIGNATURE,
    UNIT_INC,
    UNIT_INC_PER_S,
    UNIT_RPM,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

log = logging.getLogger("station.mocks.canopen")

MODE_PP, MODE_PV, MODE_PT, MODE_HM = 1, 3, 4, 6
SUPPORTED = {0, MODE_PP, MODE_PV, MODE_PT, MODE_HM}
HOMING_CURRENT_POSITION = (35, 37)  # CiA 402 homing on the current position (35 in older editions, then 37)
HOMING_METHODS = {0, *HOMING_CURRENT_POSITION}  # what 0x6098 accepts here (0: no method assigned)
ABORT_REACTIONS = {0: "none", 1: "fault", 2: "disable voltage", 3: "quick stop"}  # 0x6007
# objects that take only some values (any other: SDO abort "value range of parameter exceeded")
ACCEPTED = {
    0x6060: SUPPORTED,
    0x6098: HOMING_METHODS,
    0x6007: ABORT_REACTIONS,
    0x60A8: {UNIT_INC},  # positions in increments only
    0x60A9: {UNIT_INC_PER_S, *(UNIT_RPM | (e & 0xFF) << 24 for e in (0, -1, -2, -3))},
}
# objects whose value the drive computes on every read (``_on_read``), not a stored parameter
COMPUTED = frozenset({0x1001, 0x1003, 0x1010, 0x1011, 0x603F, 0x6041, 0x6061, 0x6062, 0x6063, 0x6064, 0x606C,
                      0x6077, 0x60FD})
EMCY_HEARTBEAT = 0x8130  # CiA 301: life guard error or heartbeat error

# NMT states (CiA 301 heartbeat values)
INITIALISING, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0, 4, 5, 127

DEFAULT_FAULT_CODE = 0x2310  # continuous over-current (CiA 402)

# SDO abort codes
ABORT_STORE = 0x08000020  # data cannot be transferred or stored
ABORT_RANGE = 0x06090030  # value range of parameter exceeded
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_STATE = 0x08000022  # not in the present device state
ABORT_INCOMPATIBLE = 0x06040043  # general parameter incompatibility (two 0x1016 entries for one node)


@dataclass
class PdoConfig:
    """One PDO as the drive's object dictionary currently describes it."""

    num: int  # 1..4
    cob_id: int
    valid: bool
    trans: int
    event_ms: int
    entries: list[tuple[int, int, int]]  # (index, subindex, bits)
    sync_count: int = 0
    last_data: bytes | None = None
    next_due: float = math.inf
    pending: bytes | None = None  # synchronous RPDO waiting for the next SYNC
    extra: dict = field(default_factory=dict)


class DriveNode(canopen.LocalNode):
    """LocalNode that tells its drive after a value was stored (LocalNode's write callbacks run before)."""

    def __init__(self, node_id: int, drive: Drive402) -> None:
        super().__init__(node_id, str(EDS_PATH))
        self._drive = drive

    def set_data(self, index, subindex, data, check_writable=False):
        super().set_data(index, subindex, data, check_writable)
        self._drive.after_write(index, subindex)


class Reading(Protocol):
    """The world as one SYNC (or one SDO read) sees it (the emulator's ``Snap``)."""

    q: Sequence[float]  # encoder positions, SI
    qd: Sequence[float]

    @property
    def contact(self) -> bool: ...


class Bus(Protocol):
    """What a drive needs of the emulator it sits on (``station.mocks.canopen.emulator.CanopenEmulator``, which
    owns the bus, the world and the scheduler thread): written here, so the drive does not import the emulator
    that builds it."""

    world: Any
    boot_delay: float  # s from NMT reset to the boot-up message
    parallel: bool  # a parallel robot: no torque modes
    home_offset_convention: str  # "position" or "zero": how the drive applies 0x607C
    limits_dirty: bool  # a torque limit was written: applied to the world at the next SYNC

    def snap(self, max_age: float = 0.002) -> Reading: ...

    def send(self, cob_id: int, data: bytes) -> None: ...

    def wake(self) -> None: ...

    def persist(self) -> None: ...

    def world_set_enabled(self, joint: int, on: bool) -> None: ...

    def world_fault(self, joint: int, code: int) -> None: ...

    def world_clear_fault(self, joint: int) -> None: ...

    def move_joint(self, joint: int, q: float, speed: float | None) -> None: ...

    def velocity_joint(self, joint: int, qd: float) -> None: ...

    def torque_joint(self, joint: int, tau: float) -> None: ...

    def hold_joint(self, joint: int) -> None: ...

    def stop_joint(self, joint: int) -> None: ...

    def update_torque_limits(self, compliance: bool = True) -> None: ...

    def rpdo_config_changed(self) -> None: ...


class Drive402:
    """One node: its object dictionary (a LocalNode), 402 state, PDOs, NMT. All world access goes through
    the emulator (``emu``), which owns the bus and the scheduler thread."""

    def __init__(self, emu: Bus, node_id: int, joint: int, encoder, serial: int,
                 contact_wired: bool = False, *, incremental: bool = False, resolution: float | None = None,
                 velocity_unit: int = UNIT_INC_PER_S, rated_torque: float = 1.0) -> None:
        self.emu = emu
        self.id = node_id
        self.joint = joint
        self.encoder = encoder
        self.serial = serial
        self.contact_wired = contact_wired
        self.incremental = incremental  # counts from where it powered up (no battery, no absolute encoder)
        revolute = emu.world.nominal.joints[joint].kind == "revolute"
        model_res = abs(encoder.counts_per_unit) * 2 * math.pi if revolute else None  # counts per motor rev
        # drive increments per model count: the drive's own resolution (0x608F) against the model's encoder
        self.resolution = float(resolution) if resolution and revolute else model_res
        self.scale = self.resolution / model_res if revolute else 1.0
        self.velocity_unit0 = velocity_unit
        self.rated_torque = float(rated_torque)  # N m (N) at the joint = 1000 per mille
        self.lock = threading.RLock()
        self._objects: dict[tuple[int, int], object] = {}
        self.node = DriveNode(node_id, self)
        # NMT and heartbeat are ours (boot-up on reset, first heartbeat one period after boot-up)
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        self.node.add_write_callback(self._check_write)
        self.node.add_read_callback(self._on_read)
        self.stored: dict[tuple[int, int], bytes] = {}  # what 0x1010 persisted (survives power cycles)
        self.nmt = INITIALISING
        self.state = NOT_READY
        self.silent_until = 0.0  # monotonic; math.inf = disconnected until power cycle
        self.last_cw = 0
        self.sp_ack = False
        self.limit_active = False
        self.halted = False
        self.target_raw: float | None = None  # internal target, raw drive counts (before origin and homing)
        self.origin = 0  # raw count at power-up of an incremental encoder (0x6063 starts at 0 there)
        self.referenced = True  # the position means the same as before power-off (absolute) or was homed
        self.homing_error = False
        self.last_mode = 0  # 0x6060 as the drive last switched to it
        self.fault_code = 0
        self.errors: list[int] = []  # 0x1003, newest first
        self.tpdos: list[PdoConfig] = []
        self.rpdos: list[PdoConfig] = []
        self.hb_next = math.inf
        self.bootup_due = math.inf
        # heartbeat consumer (0x1016): producer node -> own-clock time of its last heartbeat (None: not yet seen,
        # monitoring starts with the first one); producers whose consumer time ran out (until the next one)
        self.hb_seen: dict[int, float | None] = {}
        self.hb_lost: set[int] = set()
        self._batch: list[int] | None = None

    # ---- object dictionary helpers -------------------------------------------------------------
    def get(self, index: int, sub: int = 0):
        """A parameter's value as an SDO read would give it. Stored parameters are the hot path of every SYNC:
        their object is looked up once and the read callbacks are run only for the values the drive computes."""
        key = (index, sub)
        obj = self._objects.get(key)
        if obj is None:
            obj = self._objects[key] = self.node._find_object(index, sub)
        if index in COMPUTED:
            return obj.decode_raw(self.node.get_data(index, sub))
        data = self.node.data_store.get(index, {}).get(sub)
        if data is None:
            if obj.default is None:
                return obj.decode_raw(self.node.get_data(index, sub))
            return obj.default
        return obj.decode_raw(data)

    def put(self, index: int, value, sub: int = 0) -> None:
        """Set a value without running the write effects (the drive's own bookkeeping)."""
        obj = self.node._find_object(index, sub)
        self.node.data_store.setdefault(index, {})[sub] = obj.encode_raw(value)

    @property
    def home_offset(self) -> int:
        return int(self.get(0x607C))

    @property
    def position_offset(self) -> int:
        """Z: what the last completed homing added to the encoder count (0x2001)."""
        return int(self.get(POSITION_OFFSET))

    @property
    def frame(self) -> int:
        """0x6064 = raw count + frame."""
        return self.position_offset - self.origin

    @property
    def mode(self) -> int:
        return int(self.get(0x6060))

    def silent(self) -> bool:
        return time.monotonic() < self.silent_until

    # ---- power and NMT ------------------------------------------------------------------------
    def power_on(self) -> None:
        """Power-up / NMT reset node: volatile values back to stored-or-default, boot-up after a short delay.
        An absolute encoder keeps its count (and the stored homing result applies); an incremental one starts
        counting at 0 where the joint stands, unreferenced until homed."""
        with self.lock:
            self.node.data_store = {}
            for (index, sub), data in self.stored.items():
                self.node.data_store.setdefault(index, {})[sub] = data
            self._identity_values()
            self.silent_until = 0.0
            if self.incremental:
                self.origin = int(round(self.counts_of(self.emu.snap(max_age=0.0).q[self.joint])))
                self.put(POSITION_OFFSET, 0)
                self.referenced = False
            else:
                self.origin = 0
                self.referenced = True
            self.homing_error = False
            self._reset_402()
            self._begin_boot()

    def reset_communication(self) -> None:
        with self.lock:
            for index in [i for i in self.node.data_store if 0x1000 <= i < 0x2000]:
                del self.node.data_store[index]
            for (index, sub), data in self.stored.items():
                if 0x1000 <= index < 0x2000:
                    self.node.data_store.setdefault(index, {})[sub] = data
            self._identity_values()
            self._begin_boot()

    def _identity_values(self) -> None:
        self.put(0x1018, self.serial, 4)
        self.put(0x2000, int(self.contact_wired))
        self.put(0x6076, max(1, int(round(self.rated_torque / abs(float(self.encoder.gear)) * 1000))))
        if getattr(self.emu, "device_type", None) is not None:
            self.put(0x1000, self.emu.device_type)
        if (0x60A9, 0) not in self.stored:
            self.put(0x60A9, self.velocity_unit0)
        if self.emu.world.nominal.joints[self.joint].kind == "revolute" and (0x608F, 1) not in self.stored:
            # the drive's own scaling: its encoder's increments per motor revolution and the world joint's gear
            gear = Fraction(float(self.encoder.gear)).limit_denominator(1000)
            self.put(0x608F, round(self.resolution), 1)
            self.put(0x608F, 1, 2)
            self.put(0x6091, abs(gear.numerator), 1)
            self.put(0x6091, gear.denominator, 2)

    def _reset_402(self) -> None:
        self.last_cw = 0
        self.last_mode = int(self.get(0x6060))
        self.sp_ack = self.limit_active = self.halted = False
        self.target_raw = None
        self.fault_code = 0
        self.errors = []
        self.emu.world_set_enabled(self.joint, False)
        self.emu.world_clear_fault(self.joint)
        self.state = SOD  # NOT READY TO SWITCH ON passes automatically at power-up (transition 1)

    def _begin_boot(self) -> None:
        self.nmt = INITIALISING
        self.hb_next = math.inf
        self._consumer_changed()
        self.rebuild_pdos()
        self.bootup_due = time.monotonic() + self.emu.boot_delay
        self.emu.wake()

    def boot(self, now: float) -> None:
        """Send the boot-up message and enter PRE-OPERATIONAL; the first heartbeat follows one period later
        (sending it at once would race canopen's ``wait_for_bootup``)."""
        with self.lock:
            self.bootup_due = math.inf
            self.nmt = PRE_OPERATIONAL
            self.emu.send(0x700 + self.id, b"\x00")
            period = self.heartbeat_period()
            self.hb_next = now + period if period else math.inf

    def heartbeat_period(self) -> float:
        return int(self.get(0x1017)) / 1000.0

    def on_nmt(self, command: int) -> None:
        with self.lock:
            if self.nmt == INITIALISING:
                return
            if command == 1:
                self.nmt = OPERATIONAL
                self.rebuild_pdos()
            elif command == 2:
                self.nmt = STOPPED
            elif command == 128:
                self.nmt = PRE_OPERATIONAL
            elif command == 129:
                self.power_on()
            elif command == 130:
                self.reset_communication()

    # ---- heartbeat consumer (0x1016) ------------------------------------------------------------
    def _consumer_changed(self) -> None:
        """Monitoring of a producer starts with its first heartbeat after it was configured (CiA 301; Lenze
        8400: "the boot-up telegram counts as the first heartbeat telegram")."""
        entries = self.consumers()
        self.hb_seen = {n: self.hb_seen.get(n) for n in entries}
        self.hb_lost &= set(entries)

    def consumers(self) -> dict[int, float]:
        """Producer node id -> consumer time (s) of every active 0x1016 entry."""
        out = {}
        for k in range(1, int(self.get(0x1016, 0)) + 1):
            v = int(self.get(0x1016, k))
            node, ms = (v >> 16) & 0x7F, v & 0xFFFF
            if node and ms:
                out[node] = ms / 1000.0
        return out

    def on_heartbeat(self, producer: int, now: float) -> None:
        if producer in self.hb_seen:
            self.hb_seen[producer] = now
            self.hb_lost.discard(producer)

    def check_consumers(self, now: float) -> None:
        """A producer silent longer than its consumer time: heartbeat event (once until it is heard again):
        EMCY 0x8130, 0x1029 communication error behaviour, then the CiA 402 abort connection reaction 0x6007.
        Without a 0x1016 entry nothing happens: the drive keeps going (Lenze: response "No response")."""
        for producer, limit in self.consumers().items():
            seen = self.hb_seen.get(producer)
            if seen is None or producer in self.hb_lost or now - seen <= limit:
                continue
            self.hb_lost.add(producer)
            log.info("canopen emulator: node %d: heartbeat of node %d not heard for %.3f s of its own time "
                     "(consumer time %.3f s)", self.id, producer, now - seen, limit)
            self.heartbeat_event(producer)

    def heartbeat_event(self, producer: int) -> None:
        with self.lock:
            self.send_emcy(EMCY_HEARTBEAT, 0x11)  # generic + communication error
            behaviour = int(self.get(0x1029, 1))
            if behaviour == 0 and self.nmt == OPERATIONAL:
                self.nmt = PRE_OPERATIONAL
            elif behaviour == 2:
                self.nmt = STOPPED
            reaction = int(self.get(0x6007))
            if reaction == 1:
                self.fault(EMCY_HEARTBEAT)
            elif reaction == 2 and self.state in (RTSO, SO, OE, QSA):
                self._enter(SOD)
            elif reaction == 3 and self.state == OE:
                self._enter(QSA)
            elif reaction == 3 and self.state in (RTSO, SO):
                self._enter(SOD)

    # ---- the position frame -------------------------------------------------------------------
    def counts_of(self, q: float) -> float:
        """Raw drive increments of world encoder position ``q`` (absolute, before origin and homing)."""
        return float(self.encoder.to_counts(q)) * self.scale

    def q_of(self, counts: float) -> float:
        return float(self.encoder.to_si(counts / self.scale))

    def raw_counts(self) -> float:
        return self.counts_of(self.emu.snap().q[self.joint])

    def internal_value(self) -> int:
        """0x6063: the encoder count, incremental ones from where they powered up; homing does not change it."""
        return int(round(self.raw_counts())) - self.origin

    def position_actual(self) -> int:
        value = int(round(self.raw_counts())) + self.frame
        return max(-(1 << 31), min((1 << 31) - 1, value))

    def velocity_factor(self) -> float:
        """Drive increments per second in one unit of 0x60A9 (0x6081, 0x607F, 0x60FF, 0x606C)."""
        unit = int(self.get(0x60A9))
        exponent = struct.unpack("b", bytes([unit >> 24 & 0xFF]))[0]
        if unit & 0x00FFFFFF == UNIT_RPM:
            return self.resolution / 60.0 * 10.0 ** exponent if self.resolution else 10.0 ** exponent / 60.0
        return 10.0 ** exponent

    # ---- reads --------------------------------------------------------------------------------
    def _on_read(self, index: int, subindex: int, od) -> int | None:
        if index == 0x6041:
            return self.statusword()
        if index == 0x6064:
            return self.position_actual()
        if index == 0x6063:
            return self.internal_value()
        if index == 0x6061:
            return self.mode
        if index == 0x6062:
            return int(round(self.target_raw)) + self.frame if self.target_raw is not None \
                else self.position_actual()
        if index == 0x606C:
            qd = self.emu.snap().qd[self.joint]
            return int(round(float(self.encoder.to_counts(qd) - self.encoder.zero) * self.scale
                             / self.velocity_factor()))
        if index == 0x60FD:
            contact = self.contact_wired and self.emu.snap().contact
            return (1 << CONTACT_INPUT_BIT) if contact else 0
        if index == 0x6077:
            return self.torque_actual()
        if index == 0x603F:
            return self.fault_code
        if index == 0x1001:
            return 0x03 if self.state in (FAULT, FRA) else 0x00  # generic + current
        if index == 0x1003:
            return len(self.errors) if subindex == 0 else (
                self.errors[subindex - 1] if subindex <= len(self.errors) else 0)
        if index in (0x1010, 0x1011) and subindex >= 1:
            return 1  # the device saves/restores on command
        return None

    def torque_actual(self) -> int:
        """0x6077 (per mille of rated, the drive's sign): what the world says the motor applies now."""
        if self.state not in (OE, QSA) or self.emu.parallel:
            return 0
        tau = float(self.emu.world.joint_torque()[self.joint]) * self.encoder.direction
        return max(-32768, min(32767, int(round(tau / self.rated_torque * 1000))))

    def statusword(self) -> int:
        sw = STATE_BITS[self.state] | SW_REMOTE
        if self.mode == MODE_HM:
            # CiA 402 homing status (bits 13/12/10): error; attained; and 10 = not running (a homing on the
            # current position completes at once, so it never reads "in progress" on the wire)
            sw |= SW_TARGET_REACHED
            if self.homing_error:
                sw |= SW_HOMING_ERROR
            elif self.referenced:
                sw |= SW_HOMING_ATTAINED
            return sw
        if self.state == OE:
            if self.sp_ack:
                sw |= SW_SETPOINT_ACK
            if self.limit_active:
                sw |= SW_LIMIT
            if self._target_reached():
                sw |= SW_TARGET_REACHED
        return sw

    def _target_reached(self) -> bool:
        snap = self.emu.snap()
        still = abs(float(self.encoder.to_counts(snap.qd[self.joint]) - self.encoder.zero)) < 1.0
        if self.halted or self.mode != MODE_PP:
            return still
        if self.target_raw is None:
            return still
        window = int(self.get(0x6067))
        return still and abs(self.raw_counts() - self.target_raw) <= max(window, 1)

    # ---- writes -------------------------------------------------------------------------------
    def _check_write(self, index: int, subindex: int, od, data: bytes) -> None:
        """Validation before LocalNode stores a value (raising aborts the SDO)."""
        value = od.decode_raw(data) if od.data_type in canopen.objectdictionary.NUMBER_TYPES else None
        if index in (0x1003, 0x1010, 0x1011):
            self._check_store_restore(index, subindex, value)
        if index in ACCEPTED and value not in ACCEPTED[index]:
            raise SdoAbortedError(ABORT_RANGE)
        if index == 0x1016 and subindex >= 1 and value:
            self._check_consumer(subindex, value)
        if (0x1600 <= index < 0x1604 or 0x1A00 <= index < 0x1A04) and subindex >= 1 and value:
            self._check_mapping_entry(value, tx=index >= 0x1A00)
        if (0x1600 <= index < 0x1604 or 0x1A00 <= index < 0x1A04) and subindex == 0:
            self._check_mapping_length(index, value)

    def _check_store_restore(self, index: int, subindex: int, value) -> None:
        """0x1010 store / 0x1011 restore take only their signature; the error history 0x1003 is cleared by
        writing 0 to its count, nothing else."""
        if index == 0x1010 and subindex >= 1 and value != SAVE_SIGNATURE:
            raise SdoAbortedError(ABORT_STORE)
        if index == 0x1010 and subindex in (1, 4) and self.state not in (SOD, NOT_READY, FAULT):
            # Yaskawa Sigma-7 (SGD7S manual 15.2, 1010h): "Subindex 1 and subindex 4 can be written only in the
            # Switch ON Disabled state"; the application parameters (sub 3) at any time
            raise SdoAbortedError(ABORT_STATE)
        if index == 0x1011 and subindex >= 1 and value != LOAD_SIGNATURE:
            raise SdoAbortedError(ABORT_STORE)
        if index == 0x1003 and subindex == 0 and value != 0:
            raise SdoAbortedError(ABORT_RANGE)

    def _check_consumer(self, subindex: int, value: int) -> None:
        node = (value >> 16) & 0x7F
        for k in range(1, int(self.get(0x1016, 0)) + 1):
            other = int(self.get(0x1016, k))
            if k != subindex and (other >> 16) & 0x7F == node and other & 0xFFFF:
                raise SdoAbortedError(ABORT_INCOMPATIBLE)  # CiA 301: one consumer entry per producer

    def _check_mapping_length(self, index: int, count: int) -> None:
        """A PDO maps at most 8 objects and 64 bits (CiA 301)."""
        if count > 8:
            raise SdoAbortedError(ABORT_PDO_LENGTH)
        bits = sum((int(self.get(index, k)) & 0xFF) for k in range(1, count + 1))
        if bits > 64:
            raise SdoAbortedError(ABORT_PDO_LENGTH)

    def _check_mapping_entry(self, value: int, tx: bool) -> None:
        index, sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        try:
            obj = self.node._find_object(index, sub)
        except SdoAbortedError:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
        if not obj.pdo_mappable or bits != len(obj) or (not tx and not obj.writable):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    def after_write(self, index: int, subindex: int) -> None:
        """Effects of a stored value. While an RPDO is unpacked (``_batch``), effects run after all of its
        values are stored, controlword last, so a target and its new-setpoint bit can share one frame."""
        if self._batch is not None:
            self._batch.append(index)
            return
        with self.lock:
            self._effect(index, subindex)

    def _effect(self, index: int, subindex: int) -> None:
        if index == 0x6040:
            self._controlword(int(self.get(0x6040)))
        elif index == 0x6060:
            self._mode_changed()
        elif index == 0x6071:
            self._torque_target()
        elif index in (0x6072, 0x60E0, 0x60E1):
            self._limits_changed()
        elif index == 0x60FF:
            self._velocity_target()
        elif index == 0x1010:
            self.save(subindex)
        elif index == 0x1011:
            self.stored = {}  # defaults take effect at the next reset (CiA 301)
            self.emu.persist()
        elif index == 0x1016:
            self._consumer_changed()
            self.emu.wake()
        elif index == 0x1017:
            period = self.heartbeat_period()
            self.hb_next = time.monotonic() + period if period and self.nmt != INITIALISING else math.inf
            self.emu.wake()
        elif index == 0x1003 and subindex == 0:
            self.errors = []
        elif 0x1400 <= index < 0x1C00:
            self.rebuild_pdos()

    def save(self, scope: int) -> None:
        """0x1010: persist the parameters of ``scope`` (1 all, 2 communication, 3 application,
        4 manufacturer) so they survive NMT reset node and emulated power cycles."""
        where = {1: ("PERSIST_COMM", "PERSIST_APP", "PERSIST_MFR"), 2: ("PERSIST_COMM",),
                 3: ("PERSIST_APP",), 4: ("PERSIST_MFR",)}[scope]
        for obj in self._variables():
            if obj.storage_location not in where:
                continue
            key = (obj.index, obj.subindex)
            data = self.node.data_store.get(obj.index, {}).get(obj.subindex)
            if data is None:
                self.stored.pop(key, None)
            else:
                self.stored[key] = bytes(data)
        self.emu.persist()

    def _variables(self):
        for obj in self.node.object_dictionary.values():
            if isinstance(obj, canopen.objectdictionary.ODVariable):
                yield obj
            else:
                yield from obj.values()

    # ---- 402 state machine --------------------------------------------------------------------
    def _controlword(self, cw: int) -> None:
        prev, self.last_cw = self.last_cw, cw
        if self.state == FAULT:
            if cw & CW_FAULT_RESET and not prev & CW_FAULT_RESET:
                self._fault_reset()
            return
        new = next_state(self.state, cw)
        if new is not None:
            self._enter(new)
        if self.state == OE:
            self._operation_bits(cw, prev)

    def _operation_bits(self, cw: int, prev: int) -> None:
        """The controlword's operation mode bits in OPERATION ENABLED: halt (bit 8), and the rising edge of bit 4
        (a new set-point in profile position, the start of a homing in homing mode)."""
        halt = bool(cw & CW_HALT)
        if halt and not self.halted:
            self.halted = True
            self.emu.stop_joint(self.joint)
        elif not halt:
            self.halted = False
        if self.mode == MODE_PP:
            if cw & CW_NEW_SETPOINT and not prev & CW_NEW_SETPOINT:
                self._new_setpoint(relative=bool(cw & CW_RELATIVE))
            elif not cw & CW_NEW_SETPOINT:
                self.sp_ack = False
        elif self.mode == MODE_HM and cw & CW_HOMING_START and not prev & CW_HOMING_START and not halt:
            self._home()

    def _home(self) -> None:
        """Homing (mode 6, started by controlword bit 4 in OPERATION ENABLED). Methods 35/37 take the present
        position as the home position and complete at once: only now does the home offset 0x607C take effect
        (CiA 402 0x607C; Elmo MAN-CAN402IG 9.2: "The zero position is determined after a successful homing
        sequence"). Any other method (0: none assigned) ends in homing error (statusword bit 13)."""
        method = int(self.get(0x6098))
        if method not in HOMING_CURRENT_POSITION:
            self.homing_error = True
            return
        home = self.home_offset if self.emu.home_offset_convention == "position" else -self.home_offset
        self.put(POSITION_OFFSET, home - self.internal_value())
        self.homing_error = False
        self.referenced = True
        self.target_raw = self.raw_counts()  # holds where it is: the homing moved nothing

    def _enter(self, new: str) -> None:
        old, self.state = self.state, new
        if new == OE:
            self.emu.world_set_enabled(self.joint, True)
            self.target_raw = self.raw_counts()  # hold where it is; PP moves only on a new set-point
            self.halted = False
            if self.mode == MODE_PT:
                self._torque_target()
        elif new == QSA:
            self.emu.stop_joint(self.joint)
        elif old in (OE, QSA):
            self.emu.world_set_enabled(self.joint, False)  # brake holds the joint where it stopped
        self.sp_ack = False
        self.emu.update_torque_limits()

    def fault(self, code: int = DEFAULT_FAULT_CODE) -> None:
        """Device fault: EMCY, FAULT state (no torque, world halts), until controlword fault reset."""
        with self.lock:
            if self.state == FAULT:
                return
            self.state = FAULT
            self.fault_code = code & 0xFFFF
            self.errors = ([self.fault_code] + self.errors)[:8]
            self.sp_ack = False
            self.emu.world_fault(self.joint, self.fault_code)
            self.emu.update_torque_limits()
            self.send_emcy(self.fault_code, 0x03)

    def _fault_reset(self) -> None:
        self.fault_code = 0
        self.state = SOD
        self.emu.world_clear_fault(self.joint)
        self.send_emcy(0x0000, 0x00)  # error reset / no error

    def send_emcy(self, code: int, register: int) -> None:
        if self.silent() or self.nmt in (INITIALISING, STOPPED):
            return
        cob = int(self.get(0x1014)) & 0x7FF
        self.emu.send(cob, struct.pack("<HB5s", code, register, b"\x00" * 5))

    # ---- modes --------------------------------------------------------------------------------
    def _mode_changed(self) -> None:
        if self.mode == self.last_mode:
            return  # the same mode written again (every RPDO2 carries it): no switch
        self.last_mode = self.mode
        if self.state == OE:
            self.target_raw = self.raw_counts()  # a mode switch holds the present position
            if self.mode == MODE_PT:
                self._torque_target()
            elif self.mode != MODE_PV:
                self.emu.hold_joint(self.joint)  # also ends a torque-commanded motion
        self.emu.update_torque_limits()

    def torque_limit(self, sign: float) -> int:
        """Per mille limit for a motor torque of ``sign`` (drive frame): 0x6072 and 0x60E0 (+) / 0x60E1 (-)."""
        return min(int(self.get(0x6072)), int(self.get(0x60E0 if sign >= 0 else 0x60E1)))

    def _limits_changed(self) -> None:
        """New torque limits act from the drive's next control cycle (the next SYNC here). Raised back to its
        default (peak) torque while a following error is left (a socket pushed the joint off its target), the
        position controller pulls the joint back to its target."""
        if not self.reduced_limits() and self.state == OE and self.mode == MODE_PP and self.target_raw is not None:
            window = max(int(self.get(0x6067)), 1)
            if abs(self.raw_counts() - self.target_raw) > window and not self.halted:
                self.emu.move_joint(self.joint, self.q_of(self.target_raw), None)
        self.emu.limits_dirty = True

    def reduced_limits(self) -> bool:
        return min(int(self.get(i)) for i in (0x6072, 0x60E0, 0x60E1)) < DEFAULT_TORQUE_LIMIT

    def _torque_target(self) -> None:
        """Profile torque mode: the motor applies 0x6071 (per mille of rated) and nothing holds position; the
        world integrates what that torque and gravity do (CiA 402 profile torque; docs/world.md)."""
        if self.state != OE or self.mode != MODE_PT or self.emu.parallel:
            return
        tau = int(self.get(0x6071)) / 1000.0 * self.rated_torque * self.encoder.direction
        self.emu.torque_joint(self.joint, tau)

    def _new_setpoint(self, relative: bool) -> None:
        target = int(self.get(0x607A))
        frame = self.frame
        if relative:
            base = self.target_raw if self.target_raw is not None else self.raw_counts()
            target = int(round(base)) + frame + target
        lo, hi = int(self.get(0x607D, 1)), int(self.get(0x607D, 2))
        self.limit_active = False
        if lo < hi and not lo <= target <= hi:
            target = min(max(target, lo), hi)
            self.limit_active = True
        self.target_raw = float(target - frame)
        self.sp_ack = True
        if self.halted:
            return
        if abs(self.raw_counts() - self.target_raw) <= 0.5 and abs(self.emu.snap().qd[self.joint]) < 1e-9:
            return  # the target is where the joint stands (to the count): nothing to move
        velocity = int(self.get(0x6081))
        vmax = int(self.get(0x607F))
        if vmax:
            velocity = min(velocity, vmax)
        per_unit = self.encoder.counts_per_unit * self.encoder.gear * self.scale
        # the profile velocity in the drive's unit (0x60A9): a value meant as counts/s sent to a drive in rpm
        # asks for a speed thousands of times too high (the world caps it at the joint's maximum)
        speed = abs(velocity * self.velocity_factor() / per_unit) if velocity > 0 else None
        self.emu.move_joint(self.joint, self.q_of(self.target_raw), speed)

    def _velocity_target(self) -> None:
        if self.state != OE or self.mode != MODE_PV or self.halted:
            return
        value = int(self.get(0x60FF))
        per_unit = self.encoder.counts_per_unit * self.encoder.gear * self.scale
        self.emu.velocity_joint(self.joint, self.encoder.direction * value * self.velocity_factor() / abs(per_unit))

    # ---- PDOs ---------------------------------------------------------------------------------
    def rebuild_pdos(self) -> None:
        self.tpdos = [self._read_pdo(0x1800 + n, 0x1A00 + n, n + 1) for n in range(4)]
        self.rpdos = [self._read_pdo(0x1400 + n, 0x1600 + n, n + 1) for n in range(4)]
        now = time.monotonic()
        for p in self.tpdos:
            if p.valid and p.trans >= 254 and p.event_ms > 0:
                p.next_due = now + p.event_ms / 1000.0
        self.emu.rpdo_config_changed()
        self.emu.wake()

    def _read_pdo(self, com: int, mapping: int, num: int) -> PdoConfig:
        cob = int(self.get(com, 1))
        entries = []
        for k in range(1, int(self.get(mapping, 0)) + 1):
            v = int(self.get(mapping, k))
            if v:
                entries.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
        event = int(self.get(com, 5))
        return PdoConfig(num, cob & 0x7FF, not cob & 0x80000000, int(self.get(com, 2)), event, entries)

    def tpdo_data(self, p: PdoConfig) -> bytes:
        return b"".join(self.node.get_data(i, s) for i, s, _ in p.entries)

    def on_rpdo(self, p: PdoConfig, data: bytes) -> None:
        if self.nmt != OPERATIONAL or self.silent():
            return
        if p.trans <= 240:
            p.pending = bytes(data)  # synchronous: actuate at the next SYNC
            return
        self.apply_rpdo(p, data)

    def apply_rpdo(self, p: PdoConfig, data: bytes) -> None:
        with self.lock:
            self._batch = []
            offset = 0
            try:
                for index, sub, bits in p.entries:
                    n = bits // 8
                    chunk = bytes(data[offset:offset + n])
                    offset += n
                    if len(chunk) < n:
                        break  # short frame: the rest of the mapping is not updated
                    try:
                        self.node.set_data(index, sub, chunk)
                    except SdoAbortedError:
                        continue  # e.g. an unsupported mode: the drive keeps the old value
            finally:
                changed, self._batch = self._batch, None
            for index in sorted(set(changed), key=lambda i: (i == 0x6040, i)):
                self._effect(index, 0)
