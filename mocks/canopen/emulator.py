"""A bus of emulated CiA 402 drives serving one simulated world over python-can.

``CanopenEmulator(world, interface="virtual", channel="chan0", nodes=[1, ..., 6]).start()`` puts one
drive per joint (node order = joint order) on the bus. Station-side code talks to it with the real
``canopen`` and ``python-can`` libraries: in-process over the ``virtual`` interface, or across processes
through :class:`station.mocks.canopen.hub.SocketcandHub`.

Fault injection (``world.faults.inject(kind, device=<node id>)``):
``device_fault`` -> EMCY (code = the fault's ``code`` or 0x2310) + FAULT state + world halt;
``timeout`` -> the node is silent (no SDO answer, PDO, heartbeat or EMCY) for ``timeout_silence`` s;
``disconnect`` -> the node is silent until an emulated power cycle;
``corrupt`` -> the node's next TPDO or SDO answer is replaced by a CAN error frame (protocol error) on the wire.
Phase triggers (world file ``at: {sdo: {...}}`` / ``at: {pdo: {...}}``, docs/world.md): every SDO request a
drive receives is reported as ``notice(sdo={"node", "index", "sub", "op": "write"|"read"})`` and every RPDO as
``notice(pdo={"node", "cob_id", "num"})``; a timeout/disconnect/device fault armed by that very frame bites
before the drive answers it (a write to 0x607C that is never confirmed).
``inject_error_frame("busoff")`` puts a bus-off error frame on the wire; the station's controller is then off
the bus for ``busoff_recovery`` s (world file ``buses.canopen.busoff_recovery_s``, default 0.2 s, SocketCAN's
``restart-ms``): frames it sends in that window never reach the drives, which keep their state (a seated,
compliant arm stays compliant and enabled) until the station acts after the recovery.

A drive that loses its master (a cut-off drive, a killed station) reacts only through its heartbeat consumer
(0x1016, abort connection option code 0x6007); without one it keeps going. Vendor choices the world file makes
under ``buses.canopen`` (docs/hardware-canopen.md): ``incremental`` (encoders that count from 0 at power-up),
``position_resolution`` (increments per motor revolution), ``velocity_unit`` (``inc/s`` or ``rpm``),
``home_offset`` (``position``: 0x6064 = 0x607C at the home position, or ``zero``: CiA 402's "zero position =
home position + home offset"), ``rated_torque_nm``, ``seat_force_n``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
import numpy as np
from station.mocks.canopen.drive import (
    INITIALISING,
    MODE_PP,
    MODE_PT,
    MODE_PV,
    OE,
    OPERATIONAL,
    PRE_OPERATIONAL,
    STOPPED,
    Drive402,
    PdoConfig,
)
from station.mocks.canopen.eds import UNIT_INC_PER_S, UNIT_RPM
from station.mocks.canopen.timing import OwnClock
from station.mocks.emulator import EmulatorBase

log = logging.getLogger("station.mocks.canopen")

CAN_ERR_PROT = 0x08  # SocketCAN error class: protocol violation (what a corrupted frame causes)
CAN_ERR_BUSOFF = 0x40  # SocketCAN error class: bus off
ERROR_CLASSES = {"protocol": CAN_ERR_PROT, "busoff": CAN_ERR_BUSOFF}
STORE_FORMAT = "station-canopen-store/1"
DEFAULT_SERIAL_BASE = 0x5A100000  # of a world without a digest (no cell, no model parameters)

VELOCITY_UNITS = {"inc/s": UNIT_INC_PER_S, "rpm": UNIT_RPM, "0.1rpm": UNIT_RPM | 0xFF << 24,
                  "0.01rpm": UNIT_RPM | 0xFE << 24, "0.001rpm": UNIT_RPM | 0xFD << 24}
SEAT_FORCE_N = 20.0  # what a ball-in-cone socket pushes the tip with as the arm settles into it
MIN_LEVER_M = 1e-3  # a joint whose axis passes closer than this to the tip cannot be turned by the socket
CONFIG_KEYS = {"nodes", "contact_node", "serial_base", "timeout_silence", "busoff_recovery_s", "store_s",
               "device_type", "incremental", "position_resolution", "velocity_unit", "home_offset",
               "rated_torque_nm", "seat_force_n"}


def world_serial_base(world) -> int:
    """The drives' 0x1018 serial base, derived from the world: two worlds are two robots (never one serial)."""
    from station.mocks.world.identity import default_serial

    try:
        return int(default_serial(world, "canopen"))
    except (AttributeError, TypeError, ValueError):
        return DEFAULT_SERIAL_BASE


def _per_node(cfg: dict, key: str, nodes: list[int], kind, default):
    """``buses.canopen.KEY``: one value for every drive, or ``{node id: value}``; one-line ValueError."""
    where = f"buses.canopen.{key}"
    v = cfg.get(key, default)
    try:
        if isinstance(v, dict):
            unknown = [k for k in v if int(k) not in nodes]
            if unknown:
                raise ValueError(f"node(s) {unknown} are not on this bus ({nodes})")
            return {n: kind(v[n] if n in v else v.get(str(n), default)) for n in nodes}
        return {n: kind(v) for n in nodes}
    except (TypeError, ValueError) as e:
        raise ValueError(f"canopen emulator: {where}: {e}") from None


def _incremental(cfg: dict, nodes: list[int]) -> set[int]:
    """``incremental: true`` (every drive), ``false``, or a list of node ids whose encoders are incremental."""
    v = cfg.get("incremental", False)
    if isinstance(v, bool):
        return set(nodes) if v else set()
    if isinstance(v, list) and all(isinstance(i, int) and i in nodes for i in v):
        return set(v)
    raise ValueError(f"canopen emulator: buses.canopen.incremental: expected true, false or a list of node ids "
                     f"among {nodes}, got {v!r}")


@dataclass
class Snap:
    """The world as one SYNC (or one SDO read) sees it; the contact input is evaluated on first use."""

    t: float
    q: np.ndarray  # encoder positions, SI
    qd: np.ndarray
    world: object
    _contact: bool | None = None

    @property
    def contact(self) -> bool:
        if self._contact is None:
            self._contact = bool(self.world.contact())
        return self._contact


def _sdo_event(node_id: int, data: bytes) -> dict | None:
    """The object an SDO request frame opens (CiA 301: initiate download ccs=1, initiate upload ccs=2, block
    download ccs=6 / block upload ccs=5); None for the segments that follow an initiate."""
    ccs = data[0] >> 5
    op = {1: "write", 6: "write", 2: "read", 5: "read"}.get(ccs)
    if op is None or (ccs in (5, 6) and data[0] & 0x03):  # block sub-commands other than initiate
        return None
    return {"node": node_id, "index": data[1] | data[2] << 8, "sub": data[3], "op": op}


class _Rx(can.Listener):
    def __init__(self, emu: CanopenEmulator) -> None:
        self.emu = emu

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        stamp = msg.timestamp or time.time()
        start, end = self.emu.offbus
        if start <= stamp < end:
            return  # sent while the station's controller was bus-off: never on the wire
        self.emu.rx_stamp = stamp
        try:
            self.emu._dispatch(msg.arbitration_id, bytes(msg.data), msg.timestamp)
        except Exception:  # an emulator bug must not kill the bus thread silently
            log.exception("canopen emulator: handling frame 0x%03X failed", msg.arbitration_id)


class CanopenEmulator(EmulatorBase):
    """Drives 1..n on one CAN channel, wired to ``world`` (joint i <-> i-th node of ``nodes``): an
    ``EmulatorBase`` (``start()`` returns it, ``stop()`` idempotent, ``url``, ``power_cycle()``, context manager)."""

    def __init__(self, world, interface: str = "virtual", channel: str = "chan0", nodes=None, *,
                 contact_node: int | None = -1, store_path: str | Path | None = None,
                 timeout_silence: float = 1.0, boot_delay: float = 0.005, fault_poll: float = 0.01,
                 **bus_kwargs) -> None:
        cfg = world.bus_config("canopen")
        n = world.nominal.n_joints
        nodes = list(nodes if nodes is not None else cfg.get("nodes") or range(1, n + 1))
        if len(nodes) != n:
            raise ValueError(f"canopen emulator: {len(nodes)} node ids {nodes} for a {n}-joint robot "
                             f"({world.nominal.name}); give one node per joint")
        if len(set(nodes)) != n or not all(1 <= int(i) <= 127 for i in nodes):
            raise ValueError(f"canopen emulator: node ids must be distinct and within 1..127, got {nodes}")
        if contact_node == -1:
            contact_node = cfg.get("contact_node", nodes[-1])
        if contact_node is not None and contact_node not in nodes:
            raise ValueError(f"canopen emulator: contact node {contact_node} is not one of {nodes}")
        self.world = world
        self.interface, self.channel, self.bus_kwargs = interface, channel, bus_kwargs
        self.nodes = [int(i) for i in nodes]
        self.contact_node = contact_node
        self.store_path = Path(store_path) if store_path else None
        self.timeout_silence = float(cfg.get("timeout_silence", timeout_silence))
        self.boot_delay = boot_delay
        self.fault_poll = fault_poll
        serial_base = int(cfg["serial_base"]) if "serial_base" in cfg else world_serial_base(world)
        self.busoff_recovery = float(cfg.get("busoff_recovery_s", 0.2))
        # how long a drive takes to write its flash on "store parameters" (0x1010) before it answers
        self.store_s = float(cfg.get("store_s", 0.0))
        # wall clock (frame timestamps): the station's controller is bus-off (its frames are lost) from .. until;
        # judged by when a frame was sent, not when this process's receive thread gets to it (a frame on the wire
        # before the bus-off was heard, however late the thread is)
        self.offbus = (0.0, 0.0)
        # identity overrides for staging a wrong device (world file buses.canopen.device_type: e.g. 0x00020191)
        self.device_type = int(str(cfg["device_type"]), 0) if "device_type" in cfg else None
        # a parallel robot (Gough-Stewart legs) has no joint dynamics in the world: torques are not modelled there
        self.parallel = getattr(world.nominal, "kind", "serial") == "parallel"
        unknown = sorted(set(cfg) - CONFIG_KEYS)
        if unknown:
            raise ValueError(f"canopen emulator: buses.canopen: unknown key(s) {', '.join(unknown)} "
                             f"(known: {', '.join(sorted(CONFIG_KEYS))})")
        self.home_offset_convention = str(cfg.get("home_offset", "position"))
        if self.home_offset_convention not in ("position", "zero"):
            raise ValueError("canopen emulator: buses.canopen.home_offset: expected position or zero, got "
                             f"{self.home_offset_convention!r}")
        self.seat_force = float(cfg.get("seat_force_n", SEAT_FORCE_N))
        units = _per_node(cfg, "velocity_unit", self.nodes, str, "inc/s")
        bad = {n: u for n, u in units.items() if u not in VELOCITY_UNITS}
        if bad:
            raise ValueError(f"canopen emulator: buses.canopen.velocity_unit: {sorted(set(bad.values()))} not one "
                             f"of {', '.join(VELOCITY_UNITS)}")
        resolution = _per_node(cfg, "position_resolution", self.nodes, lambda v: None if v is None else int(v),
                               None)
        incremental = _incremental(cfg, self.nodes)
        rated = self._rated_torques(cfg)
        self.drives: dict[int, Drive402] = {}
        for j, node_id in enumerate(self.nodes):
            enc = world.nominal.joints[j].encoder
            if enc is None:
                raise ValueError(f"canopen emulator: joint {j + 1} of model {world.nominal.name} has no encoder "
                                 "scaling (counts_per_rev, gear, direction) in its model file")
            self.drives[node_id] = Drive402(
                self, node_id, j, enc, serial_base + node_id, node_id == contact_node,
                incremental=node_id in incremental, resolution=resolution[node_id],
                velocity_unit=VELOCITY_UNITS[units[node_id]], rated_torque=rated[j])
        self.clock = OwnClock()  # the drives' heartbeat consumers watch this process's own observed time
        self._load_store()
        self.network: canopen.Network | None = None
        self._rx_map: dict[int, list[tuple[Drive402, PdoConfig]]] = {}
        self._snap: Snap | None = None
        self._pinned: Snap | None = None
        self._pinned_by: int | None = None
        self._snap_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames_sent = 0
        self.sync_count = 0
        self._limits_q: np.ndarray | None = None  # where the torque limits' holding direction was last judged
        self.limits_dirty = False  # a torque limit was written: applied to the world at the next SYNC
        self.rx_stamp = 0.0  # wall-clock time of the last frame this emulator's receive thread took

    def _rated_torques(self, cfg: dict) -> list[float]:
        """Rated torque at each joint (N m, N): 1000 per mille of 0x6071/0x6072/0x6077. From the world file
        (``rated_torque_nm``: a number or one per joint), else three times what gravity loads the joint with at
        the start pose and at least the arm's largest load there (a servo sized for its arm: the peak torque,
        3000 per mille, then holds any pose)."""
        n = self.world.nominal.n_joints
        if "rated_torque_nm" in cfg:
            v = cfg["rated_torque_nm"]
            vals = [v] * n if isinstance(v, int | float) else v
            if not isinstance(vals, list) or len(vals) != n or not all(
                    isinstance(x, int | float) and math.isfinite(x) and x > 0 for x in vals):
                raise ValueError(f"canopen emulator: buses.canopen.rated_torque_nm: expected a positive number or "
                                 f"{n} of them, got {v!r}")
            return [float(x) for x in vals]
        if self.parallel:
            return [1.0] * n  # a parallel robot's screw legs: the world models no load on them (docs/world.md)
        tau = np.abs(self.world.gravity_torque())
        floor = max(float(tau.max()) if tau.size else 0.0, 1e-3)
        return [max(3.0 * float(t), floor) for t in tau]

    @property
    def url(self) -> str:
        """The robot URL of these drives (python-can interface and channel of this emulator)."""
        ids = ",".join(str(n) for n in self.nodes)
        return f"canopen+{self.interface}://{self.channel}?nodes={ids}&model={self.world.nominal.name}"

    # ---- lifecycle ----------------------------------------------------------------------------
    def _startup(self) -> None:
        bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_kwargs)
        net = canopen.Network(bus)
        net.NOTIFIER_CYCLE = 0.05  # bounds how long stop() waits for the bus thread
        for d in self.drives.values():
            net.add_node(d.node)
            # SDO and NMT go through our dispatcher (silence, NMT state, boot-up on reset)
            net.unsubscribe(0x600 + d.id, d.node.sdo.on_request)
            net.unsubscribe(0, d.node.nmt.on_command)
        net.listeners.append(_Rx(self))
        self.network = net
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"canopen-emu-{self.channel}", daemon=True)
        self._thread.start()
        net.connect()
        for d in self.drives.values():
            d.power_on()

    def _shutdown(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self.network is not None:
            net, self.network = self.network, None
            try:
                net.disconnect()
            except Exception:  # bus already gone
                log.debug("canopen emulator: disconnect failed", exc_info=True)

    def power_cycle(self, nodes=None) -> None:
        """Emulated power off/on: volatile values are lost (PDO mapping, heartbeat settings, unsaved home offset
        and homing result), parameters stored with 0x1010 survive, every drive boots (boot-up message,
        PRE-OPERATIONAL, SWITCH ON DISABLED); an incremental encoder counts from 0 again, unreferenced."""
        for node_id in nodes or self.nodes:
            self.drives[node_id].power_on()

    # ---- persistence of stored parameters (0x1010) ---------------------------------------------
    def _load_store(self) -> None:
        if not self.store_path or not self.store_path.exists():
            return
        try:
            doc = json.loads(self.store_path.read_text())
            if doc.get("format") != STORE_FORMAT:
                raise ValueError(f"format is not {STORE_FORMAT}")
            for node_id, values in doc["nodes"].items():
                d = self.drives.get(int(node_id))
                if d is None:
                    continue
                for key, hexdata in values.items():
                    index, sub = key.split(":")
                    d.stored[(int(index, 16), int(sub, 16))] = bytes.fromhex(hexdata)
        except (OSError, ValueError, KeyError, AttributeError) as e:
            raise ValueError(f"canopen emulator: parameter store {self.store_path}: {e}") from None

    def persist(self) -> None:
        if not self.store_path:
            return
        doc = {"format": STORE_FORMAT,
               "nodes": {str(d.id): {f"{i:04X}:{s:02X}": data.hex() for (i, s), data in sorted(d.stored.items())}
                         for d in self.drives.values()}}
        tmp = self.store_path.with_suffix(self.store_path.suffix + ".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(self.store_path)

    # ---- world access (called by the drives) -------------------------------------------------
    def snap(self, max_age: float = 0.002) -> Snap:
        with self._snap_lock:
            if self._pinned is not None and self._pinned_by == threading.get_ident():
                return self._pinned
            now = time.monotonic()
            if self._snap is None or now - self._snap.t > max_age:
                self._snap = Snap(now, self.world.encoder_q(), self.world.encoder_qd(), self.world)
            return self._snap

    def _pin(self, snap: Snap | None) -> None:
        """While pinned, this thread's reads see ``snap``: every TPDO of one SYNC samples the same instant."""
        with self._snap_lock:
            self._pinned, self._pinned_by = snap, threading.get_ident() if snap is not None else None

    def _invalidate(self) -> None:
        with self._snap_lock:
            self._snap = None

    def world_set_enabled(self, joint: int, on: bool) -> None:
        self.world.set_enabled(on, joint)
        self._invalidate()

    def world_fault(self, joint: int, code: int) -> None:
        self.world.fault_joint(joint, code)
        self._invalidate()

    def world_clear_fault(self, joint: int) -> None:
        self.world.clear_fault(joint)

    def move_joint(self, joint: int, q: float, speed: float | None) -> None:
        self.world.command_joint(joint, q, speed=speed)
        self._invalidate()

    def hold_joint(self, joint: int) -> None:
        """Position control holding where the joint is (ends a torque-commanded motion)."""
        q = self.world.encoder_q()[joint]
        self.world.command_joint(joint, float(q))
        self._invalidate()

    def torque_joint(self, joint: int, tau: float) -> None:
        self.world.command_torque(tau, joint)
        self._invalidate()

    def update_torque_limits(self, compliance: bool = True) -> None:
        """Each enabled drive's torque limit in the direction holding its joint takes (0x6072, 0x60E0/0x60E1, in
        N m) becomes the world's limit for that joint (a joint whose load needs more sags); drives at their
        default limits (a servo's peak torque) put none. Then the compliance the limits imply."""
        limits = np.full(len(self.nodes), np.inf)
        if self.parallel:
            if compliance:
                self.update_compliance()
            return
        if any(d.reduced_limits() for d in self.drives.values()):
            self._limits_q = self.snap().q.copy()
            hold = -self.world.gravity_torque()
            for d in self.drives.values():
                if d.reduced_limits():
                    need = hold[d.joint] * d.encoder.direction  # the motor torque holding takes, drive frame
                    limits[d.joint] = d.torque_limit(need) / 1000.0 * d.rated_torque
        if not np.array_equal(limits, self.world.torque_limit()):
            self.world.set_torque_limit(limits)
            self._invalidate()
        if compliance:
            self.update_compliance()

    def stop_joint(self, joint: int) -> None:
        """Decelerate one joint to rest at its acceleration limit (no motion if it is at rest)."""
        q, qd = self.world.encoder_q()[joint], self.world.encoder_qd()[joint]
        if abs(qd) < 1e-9:
            return
        amax = self.world.truth.joints[joint].max_acceleration
        self.world.command_joint(joint, float(q + qd * abs(qd) / (2 * amax)))
        self._invalidate()

    def velocity_joint(self, joint: int, qd: float) -> None:
        if abs(qd) < 1e-12:
            self.stop_joint(joint)
            return
        end = self.world.upper[joint] if qd > 0 else self.world.lower[joint]
        self.world.command_joint(joint, float(end), speed=abs(qd))
        self._invalidate()

    def update_compliance(self) -> None:
        on = self._yields()
        if on != self.world.compliant:
            self.world.set_compliant(on)
            self._invalidate()

    def _yields(self) -> bool:
        """Whether a socket can seat the tip: every joint the socket can turn yields to it. A joint in profile
        torque mode holds no position; a position-controlled one yields when the torque its limit leaves beyond
        holding its load (0x6072, 0x60E0/0x60E1 in the direction it would be pushed) is less than what the socket's
        seating force (``seat_force_n``) makes at that joint (force x the tip's distance from its axis). A stiff
        drive (its default, peak-torque limits) never yields; nor does any joint that is not enabled."""
        drives = list(self.drives.values())
        if not all(d.state == OE for d in drives):
            return False
        if all(d.mode == MODE_PT for d in drives):
            return True
        if not any(d.reduced_limits() for d in drives):
            return False
        if self.parallel:  # no joint dynamics for its legs: reduced limits on every leg let it yield
            return all(d.mode == MODE_PT or d.reduced_limits() for d in drives)
        q = self.world.joint_q()
        _, Jq = self.world.truth.fk_and_jacobian_q(q[None, :])
        lever = np.linalg.norm(Jq[0, :3, :], axis=0)  # tip displacement per unit joint motion (m/rad, m/m)
        hold = -self.world.gravity_torque()
        for d in drives:
            i = d.joint
            if d.mode == MODE_PT or lever[i] < MIN_LEVER_M:
                continue
            if d.mode not in (MODE_PP, MODE_PV):
                return False
            need = float(hold[i]) * d.encoder.direction
            headroom = min(d.torque_limit(1.0), d.torque_limit(-1.0)) / 1000.0 * d.rated_torque - abs(need)
            if headroom > self.seat_force * lever[i]:
                return False
        return True

    # ---- wire ---------------------------------------------------------------------------------
    def send(self, cob_id: int, data: bytes) -> None:
        net = self.network
        if net is None or net.bus is None:
            return
        try:
            net.send_message(cob_id, data)
            self.frames_sent += 1
        except can.CanError:
            log.debug("canopen emulator: send 0x%03X failed", cob_id, exc_info=True)

    def inject_error_frame(self, kind: str = "busoff") -> None:
        """Put a CAN error frame on the wire (``busoff`` or ``protocol``), as a controller reports it."""
        if kind not in ERROR_CLASSES:
            raise ValueError(f"error frame kind must be one of {', '.join(ERROR_CLASSES)}, got {kind!r}")
        net = self.network
        if net is None or net.bus is None:
            return
        msg = can.Message(arbitration_id=ERROR_CLASSES[kind], is_error_frame=True, is_extended_id=False,
                          data=bytes(8))
        if kind == "busoff":
            now = time.time()
            self.offbus = (now, now + self.busoff_recovery)
        with net.send_lock:
            net.bus.send(msg)

    def _send_tpdo(self, d: Drive402, p: PdoConfig) -> None:
        if self.world.faults.take("corrupt", d.id):
            self.inject_error_frame("protocol")  # the frame was destroyed on the wire
            return
        data = d.tpdo_data(p)
        p.last_data = data
        self.send(p.cob_id, data)

    def rpdo_config_changed(self) -> None:
        rx: dict[int, list[tuple[Drive402, PdoConfig]]] = {}
        for d in self.drives.values():
            for p in d.rpdos:
                if p.valid and p.entries:
                    rx.setdefault(p.cob_id, []).append((d, p))
        self._rx_map = rx

    def _dispatch(self, cob_id: int, data: bytes, stamp: float | None = None) -> None:
        if cob_id == 0 and len(data) >= 2:
            for d in self.drives.values():
                if data[1] in (0, d.id) and not d.silent():
                    d.on_nmt(data[0])
            return
        if cob_id == 0x80:
            self._on_sync()
            return
        if 0x700 < cob_id < 0x780 and len(data) >= 1:  # a heartbeat (or boot-up) of some node: consumers
            # heard when it was on the wire (a drive's controller takes it at once; this thread may be late)
            now = self.clock.at(stamp) if stamp else self.clock.now()
            for d in self.drives.values():
                if d.id != cob_id - 0x700 and not d.silent():
                    d.on_heartbeat(cob_id - 0x700, now)
            return
        d = self.drives.get(cob_id - 0x600) if 0x600 < cob_id < 0x680 else None
        if d is not None:
            if d.silent() or d.nmt not in (PRE_OPERATIONAL, OPERATIONAL) or len(data) < 8:
                return
            event = _sdo_event(d.id, data)
            if event is not None and self._notice(d, sdo=event):
                return  # a fault armed by this request: the drive never answers it
            if self.world.faults.take("corrupt", d.id):
                self.inject_error_frame("protocol")  # the answer is destroyed on the wire
                return
            if event is not None and event["op"] == "write" and event["index"] == 0x1010 and self.store_s > 0:
                # writing flash: the drive answers "store parameters" store_s late (CiA 301 allows it) while its
                # PDOs, SYNC answers and heartbeat go on, so the answer comes from a thread of its own
                threading.Timer(self.store_s, self._sdo_request, (d, cob_id, bytearray(data))).start()
                return
            self._sdo_request(d, cob_id, bytearray(data))
            return
        for d, p in self._rx_map.get(cob_id, ()):
            if self._notice(d, pdo={"node": d.id, "cob_id": cob_id, "num": p.num}):
                continue
            d.on_rpdo(p, data)

    @staticmethod
    def _sdo_request(d: Drive402, cob_id: int, data: bytearray) -> None:
        with d.lock:
            d.node.sdo.on_request(cob_id, data, time.time())

    def _notice(self, d: Drive402, **event) -> bool:
        """Report a wire event to the world's faults (arming those waiting for it) and act out at once what it
        armed for this drive; True if the drive is now silent and must not act on the frame."""
        faults = self.world.faults
        if not faults.waiting():
            return False
        faults.notice(**event)
        self._poll_drive(d, time.monotonic())
        return d.silent()  # a drive in FAULT still answers SDOs (and ignores enable commands itself)

    def _on_sync(self) -> None:
        self.sync_count += 1
        live = [d for d in self.drives.values() if d.nmt == OPERATIONAL and not d.silent()]
        for d in live:
            for p in d.rpdos:
                if p.valid and p.pending is not None:
                    data, p.pending = p.pending, None
                    d.apply_rpdo(p, data)
        if self.limits_dirty:  # torque limits written since the last cycle act now, with what they imply
            self.limits_dirty = False
            self.update_torque_limits()
        self._pin(self.snap(max_age=0.0))
        try:
            self._sync_tpdos(live)
        finally:
            self._pin(None)
        if any(d.reduced_limits() and d.state == OE for d in self.drives.values()):
            q = self.snap().q
            if self._limits_q is None or np.max(np.abs(q - self._limits_q)) > 1e-3:
                # the load moves with the arm: which limit (+/-) holds a joint can change too
                self.update_torque_limits(compliance=False)

    def _sync_tpdos(self, live: list[Drive402]) -> None:
        for d in live:
            with d.lock:
                for p in d.tpdos:
                    if not (p.valid and p.entries and p.trans <= 240):
                        continue
                    if p.trans == 0:  # acyclic synchronous: on SYNC, only if changed
                        if d.tpdo_data(p) != p.last_data:
                            self._send_tpdo(d, p)
                        continue
                    p.sync_count += 1
                    if p.sync_count >= p.trans:
                        p.sync_count = 0
                        self._send_tpdo(d, p)

    def wake(self) -> None:
        self._wake.set()

    def heard_until(self) -> float:
        """The drives' own time up to which they have heard the bus: now, unless this process's receive thread is
        behind (frames queued, unread): then the time of the last frame it took. A real drive's controller takes
        every frame as it passes; a heartbeat consumer must not call silent a master whose frames wait in the
        emulator's queue (a loaded test machine), yet still see a master that sends nothing at all."""
        queue = getattr(self.network.bus, "queue", None) if self.network is not None else None
        if queue is not None and queue.qsize() > 0 and self.rx_stamp:
            return self.clock.at(self.rx_stamp)
        return self.clock.now()

    # ---- scheduler: boot-up, heartbeat, event-timer TPDOs, fault polling ----------------------
    def _run(self) -> None:
        next_poll = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            self.clock.tick()
            try:
                if now >= next_poll:
                    self._poll_faults(now)
                    next_poll = now + self.fault_poll
                due = next_poll
                heard = None
                for d in self.drives.values():
                    due = min(due, self._service(d, now))
                    if d.hb_seen:
                        heard = self.heard_until() if heard is None else heard
                        d.check_consumers(heard)
            except Exception:
                log.exception("canopen emulator scheduler")
                due = now + 0.05
            self._wake.wait(max(0.0, due - time.monotonic()))
            self._wake.clear()

    def _service(self, d: Drive402, now: float) -> float:
        with d.lock:
            if now >= d.bootup_due and not d.silent():
                d.boot(now)
            if d.nmt == INITIALISING:
                return d.bootup_due
            due = math.inf
            period = d.heartbeat_period()
            if period and now >= d.hb_next:
                if not d.silent():
                    self.send(0x700 + d.id, bytes([d.nmt]))
                d.hb_next = d.hb_next + period if now - d.hb_next < period else now + period
            due = min(due, d.hb_next if period else math.inf)
            if d.nmt == OPERATIONAL:
                for p in d.tpdos:
                    if p.valid and p.entries and p.trans >= 254 and p.event_ms > 0:
                        if now >= p.next_due:
                            if not d.silent():
                                self._send_tpdo(d, p)
                            p.next_due = now + p.event_ms / 1000.0
                        due = min(due, p.next_due)
            return due

    def _poll_faults(self, now: float) -> None:
        for d in self.drives.values():
            self._poll_drive(d, now)

    def _poll_drive(self, d: Drive402, now: float) -> None:
        faults = self.world.faults
        if d.nmt in (INITIALISING, STOPPED) and not faults.peek("disconnect", d.id):
            return
        f = faults.take_fault("device_fault", d.id)
        if f is not None:
            log.info("canopen emulator: device fault on node %d", d.id)
            d.fault(f.code or 0x2310)
        # a silent drive hears nothing either: only its heartbeat consumer (if configured) can stop its joint
        if faults.take("timeout", d.id):
            d.silent_until = max(d.silent_until, now + self.timeout_silence)
        if faults.take("disconnect", d.id):
            d.silent_until = math.inf
