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
    OPERATIONAL,
    PRE_OPERATIONAL,
    STOPPED,
    Drive402,
    PdoConfig,
)

log = logging.getLogger("station.mocks.canopen")

CAN_ERR_PROT = 0x08  # SocketCAN error class: protocol violation (what a corrupted frame causes)
CAN_ERR_BUSOFF = 0x40  # SocketCAN error class: bus off
ERROR_CLASSES = {"protocol": CAN_ERR_PROT, "busoff": CAN_ERR_BUSOFF}
STORE_FORMAT = "station-canopen-store/1"
DEFAULT_SERIAL_BASE = 0x5A100000  # of a world without a digest (no cell, no model parameters)


def world_serial_base(world) -> int:
    """The drives' 0x1018 serial base, derived from the world: two worlds are two robots (never one serial)."""
    from station.mocks.world.identity import default_serial

    try:
        return int(default_serial(world, "canopen"))
    except (AttributeError, TypeError, ValueError):
        return DEFAULT_SERIAL_BASE


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
        if time.monotonic() < self.emu.offbus_until:
            return  # sent while the station's controller was bus-off: never on the wire
        try:
            self.emu._dispatch(msg.arbitration_id, bytes(msg.data))
        except Exception:  # an emulator bug must not kill the bus thread silently
            log.exception("canopen emulator: handling frame 0x%03X failed", msg.arbitration_id)


class CanopenEmulator:
    """Drives 1..n on one CAN channel, wired to ``world`` (joint i <-> i-th node of ``nodes``)."""

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
        self.offbus_until = 0.0  # monotonic: the station's controller is bus-off (its frames are lost) until then
        # identity overrides for staging a wrong device (world file buses.canopen.device_type: e.g. 0x00020191)
        self.device_type = int(str(cfg["device_type"]), 0) if "device_type" in cfg else None
        self.drives: dict[int, Drive402] = {}
        for j, node_id in enumerate(self.nodes):
            enc = world.nominal.joints[j].encoder
            if enc is None:
                raise ValueError(f"canopen emulator: joint {j + 1} of model {world.nominal.name} has no encoder "
                                 "scaling (counts_per_rev, gear, direction) in its model file")
            self.drives[node_id] = Drive402(self, node_id, j, enc, serial_base + node_id, node_id == contact_node)
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

    # ---- lifecycle ----------------------------------------------------------------------------
    def start(self) -> CanopenEmulator:
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
        return self

    def stop(self) -> None:
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

    def __enter__(self) -> CanopenEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def power_cycle(self, nodes=None) -> None:
        """Emulated power off/on: volatile values are lost, parameters stored with 0x1010 survive,
        every drive boots (boot-up message, PRE-OPERATIONAL, SWITCH ON DISABLED)."""
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
        on = all(d.compliant() for d in self.drives.values())
        if on != self.world.compliant:
            self.world.set_compliant(on)
            self._invalidate()

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
            self.offbus_until = time.monotonic() + self.busoff_recovery
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

    def _dispatch(self, cob_id: int, data: bytes) -> None:
        if cob_id == 0 and len(data) >= 2:
            for d in self.drives.values():
                if data[1] in (0, d.id) and not d.silent():
                    d.on_nmt(data[0])
            return
        if cob_id == 0x80:
            self._on_sync()
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
        self._pin(self.snap(max_age=0.0))
        try:
            self._sync_tpdos(live)
        finally:
            self._pin(None)

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

    # ---- scheduler: boot-up, heartbeat, event-timer TPDOs, fault polling ----------------------
    def _run(self) -> None:
        next_poll = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                if now >= next_poll:
                    self._poll_faults(now)
                    next_poll = now + self.fault_poll
                due = next_poll
                for d in self.drives.values():
                    due = min(due, self._service(d, now))
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
        if faults.take("timeout", d.id):
            d.silent_until = max(d.silent_until, now + self.timeout_silence)
            d.connection_lost()
        if faults.take("disconnect", d.id):
            d.silent_until = math.inf
            d.connection_lost()
