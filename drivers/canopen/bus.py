"""The wire of a CiA 402 arm: python-can bus + ``canopen.Network``, one ``canopen.BaseNode402`` per drive, the PDO
plan, the SYNC producer, TPDO rounds, heartbeat watchdog, SDO and RPDO helpers with typed errors.

Wire plan (configured by SDO at connect, then 0 SDOs per cycle):
  TPDO1 (SYNC, every cycle): statusword 0x6041, position actual 0x6064, mode display 0x6061
  TPDO2 (event timer, contact node only): digital inputs 0x60FD (bit 16 = the cell's contact input)
  RPDO1 (immediate): controlword 0x6040, target position 0x607A
  RPDO2 (immediate): mode 0x6060, profile velocity 0x6081, target torque 0x6071
A SYNC producer thread paces the TPDOs; a snapshot is one complete SYNC round. Heartbeats (0x1017, consumer
watchdog here) and CAN error frames latch typed errors into the robot's ``FaultLatch``."""

from __future__ import annotations

import collections
import contextlib
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable

from station.robot.errors import BusError, ConfigError, ConnectionLost, DeviceFault, IdentityMismatch
from station.robot.registry import bus_library
from station.robot.silence import Silence

with bus_library("python-can"):
    import can
with bus_library("canopen"):
    import canopen

from station.drivers.canopen.cia402 import SAVE  # noqa: E402 - after the wrapped bus library imports
from station.drivers.canopen.faults import FaultLatch  # noqa: E402
from station.drivers.canopen.od import CONTACT_WIRED, standard_od  # noqa: E402

log = logging.getLogger("station.drivers.canopen")

CAN_ERR_BUSOFF = 0x40
HB_MARGIN_S = 0.5  # host scheduling margin of the heartbeat consumer time


def heartbeat_consumer_s(heartbeat_ms: float) -> float:
    """Default heartbeat consumer time: 3 producer periods + 500 ms (documented in docs/hardware-canopen.md)."""
    return 3 * heartbeat_ms / 1000.0 + HB_MARGIN_S
SYNC_COB_ID = 0x80
# one round: {node: (statusword, position counts, mode display, host time.time())}
Round = dict[int, tuple[int, int, int, float]]


ERROR_FRAME_WINDOW_S = 1.0  # the URL's ``error_frames`` are tolerated within any window this long


class _BusWatch(can.Listener):
    """Error frames and receive errors on the raw bus (canopen's own listener ignores them).

    An isolated error frame is normal on a real CAN bus: the controller that saw the damaged frame signals it,
    the sender retransmits it, and CAN's own fault confinement (error counters, error passive, bus-off) handles
    a node that keeps failing. So bus-off is a fault at once, and other error frames only when more than
    ``error_frame_limit`` arrive within ``ERROR_FRAME_WINDOW_S`` (a bus that keeps corrupting frames: wiring,
    termination, bitrate)."""

    def __init__(self, bus: CanopenBus) -> None:
        self.bus = bus
        self.error_frames = 0  # since the bus was opened (diagnostics)
        self._recent: collections.deque[float] = collections.deque()

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_error_frame:
            return
        self.error_frames += 1
        cls = msg.arbitration_id & 0x1FFFFFFF
        if cls & CAN_ERR_BUSOFF:
            self.bus.faults.latch(BusError(f"CAN bus-off on {self.bus.where} (error frame class 0x{cls:X}); "
                                           "check termination, bitrate and wiring"))
            return
        now = time.monotonic()
        self._recent.append(now)
        while now - self._recent[0] > ERROR_FRAME_WINDOW_S:
            self._recent.popleft()
        limit = self.bus.error_frame_limit
        if len(self._recent) > limit:
            self.bus.faults.latch(BusError(
                f"CAN error frames on {self.bus.where}: {len(self._recent)} within {ERROR_FRAME_WINDOW_S:g} s "
                f"(class 0x{cls:X}; {limit} tolerated, {self.error_frames} since open): frames are being corrupted "
                "on the wire; check termination, shielding and bitrate"))
        else:
            log.info("CAN error frame on %s (class 0x%X, %d since open): tolerated, the frame is retransmitted",
                     self.bus.where, cls, self.error_frames)

    def on_error(self, exc: Exception) -> None:
        self.bus.faults.latch(ConnectionLost(f"CAN interface {self.bus.where} failed: {exc}"))


SDO_TIMEOUT_MS = 300.0  # python-canopen's own default answer time; a URL option (sdo_timeout_ms)
STORE_TIMEOUT_S = 3.0  # the store command (0x1010 "save") writes flash before it answers


class CanopenBus:
    """The drives ``nodes`` on one CAN network. ``open()`` connects and starts streaming; ``close()`` stops the
    threads and disconnects (the robot leaves the drives safe before)."""

    def __init__(self, nodes: list[int], faults: FaultLatch, *, interface: str, channel: str,
                 host: str | None = None, port: int | None = None, sync_period: float = 0.004,
                 heartbeat_ms: int = 100, touch_ms: int = 10, eds: str | None = None,
                 error_frame_limit: int = 1, heartbeat_timeout_ms: float | None = None,
                 sdo_timeout_ms: float = SDO_TIMEOUT_MS) -> None:
        self.nodes = list(nodes)
        self.faults = faults
        self.interface, self.channel, self.host, self.port = interface, channel, host, port
        self.where = f"{interface} {host}:{port}/{channel}" if host else f"{interface} {channel}"
        self.sync_period = sync_period
        self.heartbeat_ms = heartbeat_ms
        # consumer time: 3 missed producer periods plus a margin for the host's scheduling (a loaded 2-core PC
        # stalled the station's receive thread by > 400 ms: "heartbeat lost (517 ms)" with a 200 ms margin)
        self.hb_timeout = (heartbeat_timeout_ms / 1000.0 if heartbeat_timeout_ms
                           else heartbeat_consumer_s(heartbeat_ms))
        self.touch_ms = touch_ms
        self.sdo_timeout = sdo_timeout_ms / 1000.0
        self.error_frame_limit = max(1, error_frame_limit)
        self.eds = eds
        self.contact_node: int | None = None
        self.drives: dict[int, canopen.BaseNode402] = {}
        self.sync_frames = 0
        self.cmd_seq = 0  # SYNC count when the last RPDO was sent: rounds after it reflect every command
        self.changed_at = 0.0  # monotonic: last RPDO sent or command confirmed (a touch reading must be newer)
        self._cv = threading.Condition()
        self._seq = 0
        self._contact: tuple[float, bytes] | None = None  # (monotonic, data) of the last contact TPDO2
        self._history: dict[int, dict[int, tuple[int, int, int, float]]] = {n: {} for n in nodes}
        self._latest: dict[int, tuple[int, int, int, int, float]] = {}
        self._last_hb: dict[int, float] = {}
        # per node: heartbeat silence while the watchdog watches (the station's own scheduling gaps not counted)
        self._hb_silence: dict[int, Silence] = {}
        self._tx_lock = threading.RLock()
        self._stop = threading.Event()
        self.closing = False  # set once the robot starts closing: a boot-up message then is no fault
        self._threads: list[threading.Thread] = []
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # bounds how long close() waits for the bus thread
        self._watch = _BusWatch(self)
        faults.on_first.append(self._wake)

    # ---- connect ------------------------------------------------------------------------------------------
    def _open_can(self) -> can.BusABC:
        try:
            if self.interface == "socketcand":
                # python-can retries a refused connect for 10 s; probe first for a prompt, clear error
                with socket.create_connection((self.host, self.port), timeout=2.0):
                    pass
                return can.Bus(interface="socketcand", host=self.host, port=self.port, channel=self.channel,
                               tcp_tune=True)
            return can.Bus(interface=self.interface, channel=self.channel)
        except (OSError, can.CanError) as e:
            raise ConnectionLost(f"cannot open CAN bus {self.where}: {e}") from None

    def open(self, contact: int | None | str, on_emcy: Callable[[int, object], None]) -> None:
        """Connect every drive (must be CiA 402), find the contact node (``"auto"``: 0x2000 = 1), write the PDO
        plan and heartbeat time, go operational, start SYNC and the watchdog; returns after the first round."""
        self.network.bus = self._open_can()
        self.network.listeners.append(self._watch)
        self.network.connect()
        for node_id in self.nodes:
            od = canopen.import_od(self.eds, node_id) if self.eds else standard_od(node_id)
            node = canopen.BaseNode402(node_id, od)
            self.network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
            self.drives[node_id] = node
        for node_id, node in self.drives.items():
            dtype = self._first_contact(node_id)
            if dtype & 0xFFFF != 402:
                raise IdentityMismatch(f"canopen node {node_id} on {self.where} is not a CiA 402 drive "
                                  f"(device type 0x{dtype:08X})")
            node.nmt.state = "PRE-OPERATIONAL"
        self.contact_node = self._find_contact(contact)
        for node_id, node in self.drives.items():
            self._configure_pdos(node, node_id == self.contact_node)
            node.setup_402_state_machine(read_pdos=False)
            node.tpdo[1].add_callback(lambda m, n=node_id: self._on_tpdo1(n, m))
            if node_id == self.contact_node:
                node.tpdo[2].add_callback(self._on_tpdo2)
            node.emcy.add_callback(lambda e, n=node_id: on_emcy(n, e))
            node.nmt.add_heartbeat_callback(lambda s, n=node_id: self._on_heartbeat(n, s))
            self.sdo_write(node_id, 0x1017, self.heartbeat_ms)
            self._last_hb[node_id] = time.monotonic()
            self._hb_silence[node_id] = Silence(own_gap=0.1)
        for node in self.drives.values():
            node.nmt.state = "OPERATIONAL"
        for target, name in ((self._sync_loop, "sync"), (self._watchdog, "watchdog")):
            t = threading.Thread(target=target, name=f"canopen-{name}", daemon=True)
            t.start()
            self._threads.append(t)

    def _first_contact(self, node_id: int, attempts: int = 3) -> int:
        """Device type 0x1000, asked up to ``attempts`` times: a drive still booting (power-up, or NMT reset just
        before the station connects) ignores SDO requests until its boot-up message."""
        for attempt in range(attempts):
            try:
                return self.sdo_read(node_id, 0x1000)
            except ConnectionLost:
                if attempt == attempts - 1:
                    raise
        raise AssertionError("unreachable")

    def _find_contact(self, contact: int | None | str) -> int | None:
        if contact != "auto":
            if contact is not None and contact not in self.drives:
                raise ConfigError(f"canopen: contact node {contact} is not one of {self.nodes}")
            return contact
        for node_id, node in self.drives.items():
            try:
                if node.sdo.upload(CONTACT_WIRED, 0)[0] == 1:
                    return node_id
            except (canopen.SdoAbortedError, KeyError, IndexError):
                continue  # not the station's drive, or not wired: no contact input there
            except canopen.SdoCommunicationError as e:
                raise ConnectionLost(f"canopen node {node_id} on {self.where}: {e}") from None
        return None

    def _configure_pdos(self, node: canopen.BaseNode402, contact: bool) -> None:
        for n in range(1, 5):
            for maps, base in ((node.tpdo, 0x180), (node.rpdo, 0x200)):
                m = maps[n]
                m.clear()
                m.cob_id = base + 0x100 * (n - 1) + node.id
                m.enabled = False
                m.trans_type = 255
                m.event_timer = 0 if maps is node.tpdo else None
        t1, t2, r1, r2 = node.tpdo[1], node.tpdo[2], node.rpdo[1], node.rpdo[2]
        for idx in (0x6041, 0x6064, 0x6061):
            t1.add_variable(idx)
        t1.trans_type, t1.enabled = 1, True
        if contact:
            t2.add_variable(0x60FD)
            t2.trans_type, t2.event_timer, t2.enabled = 255, self.touch_ms, True
        for idx in (0x6040, 0x607A):
            r1.add_variable(idx)
        for idx in (0x6060, 0x6081, 0x6071):
            r2.add_variable(idx)
        r1.enabled = r2.enabled = True
        try:
            node.tpdo.save()
            node.rpdo.save()
        except canopen.SdoCommunicationError as e:
            raise ConnectionLost(f"canopen node {node.id}: PDO configuration failed: {e}") from None
        except canopen.SdoAbortedError as e:
            raise DeviceFault(f"canopen node {node.id} refused the PDO mapping: {e}", device=f"node {node.id}",
                              code=e.code) from None

    # ---- SDO (configuration only, never in the streaming cycle) ---------------------------------------------
    @contextlib.contextmanager
    def _sdo(self, node_id: int, verb: str, index: int, sub: int | None):
        """One SDO transfer's errors as the station's: no answer -> ConnectionLost, an abort -> DeviceFault."""
        obj = f"0x{index:04X}" if sub is None else f"0x{index:04X}:{sub:02X}"
        try:
            yield
        except canopen.SdoCommunicationError as e:
            raise ConnectionLost(f"canopen node {node_id} on {self.where} does not answer "
                                 f"(SDO {verb} {obj}: {e})") from None
        except canopen.SdoAbortedError as e:
            raise DeviceFault(f"canopen node {node_id}: SDO {verb} {obj} aborted: {e}", device=f"node {node_id}",
                              code=e.code) from None

    def sdo_read(self, node_id: int, index: int, sub: int = 0):
        node = self.drives[node_id]
        with self._sdo(node_id, "read", index, sub):
            return (node.sdo[index][sub] if sub else node.sdo[index]).raw

    def sdo_read_u32(self, node_id: int, index: int, sub: int) -> int | None:
        """An UNSIGNED32 by raw SDO upload (also for objects outside the driver's dictionary); None when the
        drive does not have the object (SDO abort: optional objects such as 0x608F)."""
        node = self.drives[node_id]
        try:
            with self._sdo(node_id, "read", index, sub):
                data = node.sdo.upload(index, sub)
        except DeviceFault:
            return None
        return int.from_bytes(bytes(data[:4]).ljust(4, b"\0"), "little")

    def sdo_write(self, node_id: int, index: int, value, sub: int | None = None, timeout: float | None = None) -> None:
        """``timeout`` (s) replaces the URL's ``sdo_timeout_ms`` for this one transfer (the store command)."""
        node = self.drives[node_id]
        usual = node.sdo.RESPONSE_TIMEOUT
        if timeout is not None:
            node.sdo.RESPONSE_TIMEOUT = max(timeout, usual)
        try:
            with self._sdo(node_id, "write", index, sub):
                if sub is None:
                    node.sdo[index].raw = value
                else:
                    node.sdo[index][sub].raw = value
        finally:
            node.sdo.RESPONSE_TIMEOUT = usual

    def store_parameters(self, node_id: int) -> None:
        """0x1010:01 "save": CiA 301 lets a drive answer only after its non-volatile memory is written, which
        takes a real drive hundreds of ms (longer than an ordinary SDO answer), so this transfer waits
        ``STORE_TIMEOUT_S`` at least."""
        self.sdo_write(node_id, 0x1010, SAVE, sub=1, timeout=STORE_TIMEOUT_S)

    # ---- RPDOs (immediate) -------------------------------------------------------------------------------
    def send_rpdo1(self, node_id: int, cw: int, target: int | None = None) -> None:
        """Controlword (and target position, counts; else the last one set)."""
        with self._tx_lock:
            self.cmd_seq, self.changed_at = self._seq, time.monotonic()
            m = self.drives[node_id].rpdo[1]
            if target is not None:
                m[0x607A].raw = int(target)
            m[0x6040].raw = cw
            m.transmit()

    def preset_target(self, node_id: int, counts: int) -> None:
        """Target position the next RPDO1 carries (nothing sent now)."""
        self.drives[node_id].rpdo[1][0x607A].raw = int(counts)

    def send_rpdo2(self, node_id: int, mode: int, velocity: int, torque: int) -> None:
        with self._tx_lock:
            self.cmd_seq, self.changed_at = self._seq, time.monotonic()
            m = self.drives[node_id].rpdo[2]
            m[0x6060].raw = mode
            m[0x6081].raw = max(0, min(int(velocity), 0xFFFFFFFF))
            m[0x6071].raw = int(torque)
            m.transmit()

    def mark_changed(self) -> None:
        """A command was confirmed now: contact readings from before it are stale."""
        self.changed_at = time.monotonic()

    # ---- streaming: SYNC producer, TPDO rounds ------------------------------------------------------------
    def _sync_loop(self) -> None:
        t_next = time.monotonic()
        while not self._stop.is_set():
            with self._cv:
                self._seq += 1
            try:
                self.network.send_message(SYNC_COB_ID, b"")
                self.sync_frames += 1
            except (can.CanError, OSError, AttributeError) as e:
                self.faults.latch(ConnectionLost(f"cannot send SYNC on {self.where}: {e}"))
            t_next += self.sync_period
            delay = t_next - time.monotonic()
            if delay < -self.sync_period:  # fell behind (loaded machine): do not burst
                t_next = time.monotonic()
                delay = 0.0
            self._stop.wait(max(0.0, delay))

    def _on_tpdo1(self, node_id: int, m) -> None:
        data = bytes(m.data)
        if len(data) < 7:
            return
        sw, pos, mode = struct.unpack_from("<Hib", data)
        now = time.time()
        with self._cv:
            seq = self._seq
            hist = self._history[node_id]
            hist[seq] = (sw, pos, mode, now)
            if len(hist) > 16:
                del hist[min(hist)]
            self._latest[node_id] = (seq, sw, pos, mode, now)
            self._cv.notify_all()

    def _on_tpdo2(self, m) -> None:
        with self._cv:
            self._contact = (time.monotonic(), bytes(m.data))

    def _wake(self) -> None:
        with self._cv:
            self._cv.notify_all()

    def _complete_after(self, s0: int) -> Round | None:
        seqs = None
        for hist in self._history.values():
            s = {k for k in hist if k > s0}
            seqs = s if seqs is None else seqs & s
            if not seqs:
                return None
        best = max(seqs)
        return {n: self._history[n][best] for n in self.nodes}

    def _fresh_after(self, s0: int) -> Round | None:
        """Latest TPDO of every node received after SYNC ``s0`` (rounds not aligned: a loaded bus/host)."""
        out = {}
        for n, hist in self._history.items():
            newer = [k for k in hist if k > s0]
            if not newer:
                return None
            out[n] = hist[max(newer)]
        return out

    def round(self, timeout: float | None = None) -> Round:
        """A complete SYNC round started after this call. If the replies of one SYNC do not line up within 3
        periods, every node's newest reply after the call. A latched fault is raised instead."""
        timeout = timeout or max(1.0, 20 * self.sync_period)
        start = time.monotonic()
        with self._cv:
            s0 = self._seq
            snap = None
            while snap is None and self.faults.error is None:
                snap = self._complete_after(s0)
                waited = time.monotonic() - start
                if snap is None and waited > 3 * self.sync_period:
                    snap = self._fresh_after(s0)
                if snap is None:
                    if waited > timeout:
                        break
                    self._cv.wait(min(self.sync_period, timeout - waited + 1e-3))
        if snap is None:
            self.faults.raise_if_latched()
            with self._cv:
                missing = [n for n in self.nodes if not any(k > s0 for k in self._history[n])]
            err = ConnectionLost(f"canopen {self.where}: no complete SYNC round within {timeout:.2f} s "
                                 f"(no TPDO from node(s) {missing or '?'})")
            self.faults.latch(err)
            raise err
        return snap

    def recent(self) -> Round:
        """The newest complete SYNC round if it already reflects every command sent so far and is at most one
        cycle old (the drives' state and position as of now, to within one cycle); otherwise the next round."""
        with self._cv:
            floor = max(self.cmd_seq, self._seq - 2)
            snap = self._complete_after(floor)
        return snap if snap is not None else self.round()

    def latest(self) -> dict[int, tuple[int, int, int, int, float]]:
        """Newest TPDO1 per node without waiting: ``{node: (sync seq, statusword, counts, mode, t)}``."""
        with self._cv:
            return dict(self._latest)

    def digital_inputs(self) -> int:
        """0x60FD of the contact node as sampled after the last command took effect (a move that ended, a
        mode switch) and within one event period of now: the newest TPDO2 if it is such, else the next one."""
        with self._cv:
            last = self._contact
        now = time.monotonic()
        if last is None or last[0] <= self.changed_at or now - last[0] > 1.5 * self.touch_ms / 1000.0:
            pdo = self.drives[self.contact_node].tpdo[2]
            if pdo.wait_for_reception(timeout=max(0.2, 5 * self.touch_ms / 1000.0)) is None:
                self.faults.raise_if_latched()
                raise ConnectionLost(f"canopen node {self.contact_node}: no digital-input TPDO within "
                                     f"{5 * self.touch_ms} ms")
            last = (now, bytes(pdo.data))  # canopen stores the data before it runs our callback
        return struct.unpack_from("<I", last[1].ljust(4, b"\0"))[0]

    # ---- heartbeats ------------------------------------------------------------------------------------------
    def _on_heartbeat(self, node_id: int, state: int) -> None:
        self._last_hb[node_id] = time.monotonic()
        if (silence := self._hb_silence.get(node_id)) is not None:
            silence.reset()
        if state == 0 and not self.closing:
            self.faults.latch(ConnectionLost(f"canopen node {node_id} rebooted (boot-up message while running); "
                                             "reopen the robot"), fatal=True)

    def silent_nodes(self) -> list[int]:
        """Nodes whose heartbeat is overdue now."""
        now = time.monotonic()
        return [n for n, t in self._last_hb.items() if now - t > self.hb_timeout]

    def _watchdog(self) -> None:
        step = min(0.05, self.heartbeat_ms / 4000.0)
        while not self._stop.wait(step):
            for node_id, silence in list(self._hb_silence.items()):
                # a loaded station PC that did not run this thread (nor the receive thread) for a while has not
                # seen the heartbeats queued meanwhile: its own gap is not the drive's silence
                quiet = silence.tick()
                if quiet > self.hb_timeout:
                    self.faults.latch(ConnectionLost(
                        f"canopen node {node_id} on {self.where}: heartbeat lost ({quiet * 1e3:.0f} ms "
                        f"without one, expected every {self.heartbeat_ms} ms); robot stopped"))
                    if self.link_closed():
                        # python-can's socketcand client spins on a closed socket (select says readable,
                        # recv returns b""): stop its receive thread instead of burning a core until close()
                        self.faults.latch(ConnectionLost(f"socketcand server {self.host}:{self.port} closed the "
                                                         "connection; reopen the robot"), fatal=True)
                        with contextlib.suppress(Exception):
                            self.network.notifier.stop(1.0)
                        return
                    break

    def link_closed(self) -> bool:
        """The transport is gone for good: the socketcand TCP connection reached end-of-file."""
        sock = getattr(self.network.bus, "_SocketCanDaemonBus__socket", None)
        if self.interface != "socketcand" or sock is None:
            return False
        try:
            return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            return False
        except OSError:
            return True

    # ---- end ----------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop SYNC and the watchdog, disconnect (the drives were left safe by the robot)."""
        self.closing = True
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        with contextlib.suppress(Exception):
            self.network.disconnect()
