"""The wire of a CiA 402 arm: python-can bus (any interface python-can speaks) + ``canopen.Network``, one
``canopen.BaseNode402`` per drive, the station's own heartbeat producer, the PDO plan, the SYNC producer, TPDO
rounds, heartbeat watchdog, SDO and RPDO helpers with typed errors.

Wire plan (configured by SDO at connect, then 0 SDOs per cycle):
  TPDO1 (SYNC, every cycle): statusword 0x6041, position actual 0x6064, mode display 0x6061
  TPDO2 (event timer, contact node only): digital inputs 0x60FD (bit 16 = the cell's contact input)
  RPDO1 (immediate): controlword 0x6040, target position 0x607A
  RPDO2 (immediate): mode 0x6060, profile velocity 0x6081, target torque 0x6071
A SYNC producer thread paces the TPDOs; a snapshot is one complete SYNC round. The station's node (``master_id``)
produces a heartbeat (0x1017, python-canopen's ``LocalNode``) that every drive consumes (0x1016) with its abort
connection reaction (0x6007): a killed station stops the arm. Drive heartbeats (consumer watchdog here), python-can's
bus state and CAN error frames (where the interface delivers them; socketcand never does) latch typed errors into
the robot's ``FaultLatch``. Every timeout counts only time the station could observe (``timing``)."""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable

from station.robot.errors import (
    BusError,
    ConfigError,
    ConnectionLost,
    DeviceFault,
    IdentityMismatch,
    StationError,
)
from station.robot.registry import bus_library
from station.robot.silence import Silence

with bus_library("python-can"):
    import can
with bus_library("canopen"):
    import canopen

from station.drivers.canopen.cia402 import SAVE, STORE_APPLICATION  # noqa: E402 - after the bus library imports
from station.drivers.canopen.faults import FaultLatch  # noqa: E402
from station.drivers.canopen.interfaces import open_can  # noqa: E402
from station.drivers.canopen.od import CONTACT_WIRED, master_od, standard_od  # noqa: E402
from station.drivers.canopen.timing import Deadline, HostWatch  # noqa: E402

log = logging.getLogger("station.drivers.canopen")

CAN_ERR_BUSOFF = 0x40
HB_MARGIN_S = 0.5  # host scheduling margin of the heartbeat consumer time
SDO_RETRIES_AFTER_STALL = 3  # an SDO that timed out while this process was not scheduled is asked again
SDO_PATIENCE = 10  # answer times an SDO is asked again while its drive is visibly alive (PDOs, heartbeats)
STRUCT = {"u8": "<B", "i8": "<b", "u16": "<H", "i16": "<h", "u32": "<I", "i32": "<i"}
# application parameters (stored by 0x1010:03) the station sets while it runs: put back as found before a store
RUNTIME_APPLICATION = ((0x6081, "u32"), (0x6007, "i16"))
RATED_TORQUE = 1000  # per mille: the rated torque every drive gives (a torque limit below it is a soft arm)


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
        # python-can's socketcand client puts the formatted traceback into its error's text: its first line only
        text = (str(exc).strip().splitlines() or [type(exc).__name__])[0].strip()
        self.bus.faults.latch(ConnectionLost(f"CAN interface {self.bus.where} failed: {text}"))


class MasterLoss:
    """How each drive reacts when the station's heartbeat stops: its consumer time (0x1016, ms) and the CiA 402
    abort connection option code (0x6007: 1 fault, 2 disable voltage, 3 quick stop); ``reaction`` None: the
    drives are not told to watch the station (the URL said so)."""

    REACTIONS = {"fault": 1, "disable": 2, "quick_stop": 3}

    def __init__(self, master_id: int, heartbeat_ms: int, timeout_ms: float, reaction: str | None) -> None:
        self.master_id, self.heartbeat_ms, self.timeout_ms = master_id, heartbeat_ms, timeout_ms
        self.reaction = reaction


SDO_TIMEOUT_MS = 300.0  # python-canopen's own default answer time; a URL option (sdo_timeout_ms)
STORE_TIMEOUT_S = 3.0  # the store command (0x1010 "save") writes flash before it answers


class CanopenBus:
    """The drives ``nodes`` on one CAN network. ``open()`` connects and starts streaming; ``close()`` stops the
    threads and disconnects (the robot leaves the drives safe before)."""

    def __init__(self, nodes: list[int], faults: FaultLatch, *, interface: str, channel: str,
                 host: str | None = None, port: int | None = None, sync_period: float = 0.004,
                 heartbeat_ms: int = 100, touch_ms: int = 10, eds: str | None = None,
                 error_frame_limit: int = 1, heartbeat_timeout_ms: float | None = None,
                 sdo_timeout_ms: float = SDO_TIMEOUT_MS, bitrate: int | None = None,
                 master: MasterLoss | None = None) -> None:
        self.nodes = list(nodes)
        self.faults = faults
        self.interface, self.channel, self.host, self.port = interface, channel, host, port
        self.bitrate = bitrate
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
        self.master = master
        self.master_node: canopen.LocalNode | None = None
        self.consumer_subs: dict[int, int] = {}  # node -> 0x1016 sub-index the station's entry went into
        # application parameters the station changes at run time, as each drive had them before (stored as found)
        self.found: dict[int, dict[tuple[int, str], int]] = {}
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
        self.nmt_states: dict[int, int] = {}  # node -> NMT state of its last heartbeat (5 operational, 127 pre-op)
        self._alive: dict[int, float] = {}  # node -> monotonic time of its last TPDO1 or heartbeat
        # per node: heartbeat silence while the watchdog watches (the station's own scheduling gaps not counted)
        self._hb_silence: dict[int, Silence] = {}
        self.sched = HostWatch(own_gap=0.1)  # the watchdog's view of this process's scheduling gaps
        self._tx_lock = threading.RLock()
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None  # per_node's SDO workers
        self._stop = threading.Event()
        self.closing = False  # set once the robot starts closing: a boot-up message then is no fault
        self._consumers_from = 0.0  # monotonic: every drive's consumer has been sent a heartbeat by then
        self._threads: list[threading.Thread] = []
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # bounds how long close() waits for the bus thread
        self._watch = _BusWatch(self)
        faults.on_first.append(self._wake)

    # ---- connect ------------------------------------------------------------------------------------------
    def _open_can(self) -> can.BusABC:
        return open_can(self.interface, self.channel, host=self.host, port=self.port, bitrate=self.bitrate,
                        where=self.where)

    def open(self, contact: int | None | str, on_emcy: Callable[[int, object], None]) -> None:
        """Connect every drive (must be CiA 402), find the contact node (``"auto"``: 0x2000 = 1), write the PDO
        plan and heartbeat time, start the station's own heartbeat and each drive's consumer of it, go
        operational, start SYNC and the watchdog; returns after the first round."""
        self.network.bus = self._open_can()
        self.network.listeners.append(self._watch)
        self.network.connect()
        if self.master is not None and self.master.master_id in self.nodes:
            raise ConfigError(f"canopen: master_id={self.master.master_id} is one of the drives' node ids "
                              f"{self.nodes}; give the station a node id of its own")
        for node_id in self.nodes:
            od = canopen.import_od(self.eds, node_id) if self.eds else standard_od(node_id)
            node = canopen.BaseNode402(node_id, od)
            self.network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
            self.drives[node_id] = node
        for target, name in ((self._watchdog, "watchdog"),):  # host gaps are watched from now (SDO retries)
            t = threading.Thread(target=target, name=f"canopen-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        for node_id, node in self.drives.items():
            dtype = self._first_contact(node_id)
            if dtype & 0xFFFF != 402:
                raise IdentityMismatch(f"canopen node {node_id} on {self.where} is not a CiA 402 drive "
                                       f"(device type 0x{dtype:08X})")
            node.nmt.state = "PRE-OPERATIONAL"
        self._reload_soft_drives()
        self.contact_node = self._find_contact(contact)
        for node_id in self.drives:
            self.found[node_id] = {key: v for key in RUNTIME_APPLICATION
                                   if (v := self.read_opt(node_id, key[0], 0, key[1])) is not None}
        self._start_master()

        def configure(node_id: int) -> None:  # every drive at once: each has its own SDO channel
            node = self.drives[node_id]
            self._configure_pdos(node, node_id == self.contact_node)
            self.sdo_write(node_id, 0x1017, self.heartbeat_ms)
            self._configure_consumer(node_id)

        self.per_node(self.nodes, configure)
        self._heartbeat_for_the_consumers()
        for node_id, node in self.drives.items():
            node.setup_402_state_machine(read_pdos=False)
            node.tpdo[1].add_callback(lambda m, n=node_id: self._on_tpdo1(n, m))
            if node_id == self.contact_node:
                node.tpdo[2].add_callback(self._on_tpdo2)
            node.emcy.add_callback(lambda e, n=node_id: on_emcy(n, e))
            node.nmt.add_heartbeat_callback(lambda s, n=node_id: self._on_heartbeat(n, s))
            self._last_hb[node_id] = time.monotonic()
            self._hb_silence[node_id] = Silence(own_gap=0.1)
        for node in self.drives.values():
            node.nmt.state = "OPERATIONAL"
        t = threading.Thread(target=self._sync_loop, name="canopen-sync", daemon=True)
        t.start()
        self._threads.append(t)

    def _start_master(self) -> None:
        """The station's heartbeat (CiA 301 producer, python-canopen ``LocalNode`` on node ``master_id``): sent by
        python-can's periodic task of this interface, so it stops when this process does."""
        if self.master is None:
            return
        node = canopen.LocalNode(self.master.master_id, master_od(self.master.master_id))
        self.network.add_node(node)
        node.nmt.state = "OPERATIONAL"
        node.sdo[0x1017].raw = self.master.heartbeat_ms  # starts the periodic heartbeat
        self.master_node = node
        self._watch_heartbeat_task()

    def _watch_heartbeat_task(self) -> None:
        # python-can's periodic task re-raises a send error in its thread (a traceback on stderr) unless it has
        # an error handler: a heartbeat that cannot be sent is a lost link, said once by the latch
        task = getattr(getattr(self.master_node.nmt, "_send_task", None), "_task", None)
        if task is not None and hasattr(task, "on_error"):
            task.on_error = self._heartbeat_send_failed

    def _heartbeat_for_the_consumers(self) -> None:
        """A drive's heartbeat consumer watches a producer only from the first heartbeat it hears after its 0x1016
        entry is written (CiA 301, heartbeat protocol: monitoring starts with the first heartbeat received; the
        emulator does the same). The heartbeat task starts again now, so its first heartbeat goes out at once;
        ``consumers_watching()`` waits until one period and a half has passed since: no drive is enabled that
        would not notice the station go silent (a drive enabled in that window, on a loaded host, kept going
        after a bus-off took the station off the bus)."""
        if self.master_node is None:
            return
        self.master_node.nmt.start_heartbeat(self.master.heartbeat_ms)
        self._watch_heartbeat_task()
        self._consumers_from = time.monotonic() + 1.5 * self.master.heartbeat_ms / 1000.0

    def consumers_watching(self) -> None:
        """Return once every drive's consumer has been sent a heartbeat since it was configured (at most one
        heartbeat period and a half after connect; at once afterwards)."""
        wait = self._consumers_from - time.monotonic()
        if wait > 0:
            time.sleep(wait)

    def _heartbeat_send_failed(self, exc: Exception) -> bool:
        if not self.closing:
            self.faults.latch(ConnectionLost(f"cannot send the station's heartbeat on {self.where}: {exc}"))
        return False  # stop the task: the drives' consumers react as they were told to

    def _configure_consumer(self, node_id: int) -> None:
        """Each drive watches the station's heartbeat: a 0x1016 entry (master id, consumer time) in the sub-index
        that already names the station, else the first free one (another producer's entry is left alone), and
        the abort connection option code 0x6007 (the reaction when the station goes silent). A drive without
        them is refused unless the URL says ``on_master_loss=none``."""
        m = self.master
        if m is None or m.reaction is None:
            return
        count = self.read_opt(node_id, 0x1016, 0, "u8")
        if not count:
            raise ConfigError(f"canopen node {node_id}: no heartbeat consumer (0x1016): it would keep moving if the "
                              "station died; configure the drive's own guarding and give on_master_loss=none")
        free = None
        for sub in range(1, count + 1):
            entry = self.read_obj(node_id, 0x1016, sub, "u32")
            if (entry >> 16) & 0x7F == m.master_id:
                free = sub
                break
            if free is None and not entry & 0xFFFF:
                free = sub
        if free is None:
            raise ConfigError(f"canopen node {node_id}: every heartbeat consumer entry (0x1016:01..{count:02X}) is "
                              "in use; free one for the station or give on_master_loss=none")
        try:
            self.write_obj(node_id, 0x6007, 0, "i16", MasterLoss.REACTIONS[m.reaction])
        except DeviceFault as e:
            raise ConfigError(f"canopen node {node_id}: abort connection option code 0x6007 = {m.reaction} refused "
                              f"({e}); choose another on_master_loss") from None
        self.write_obj(node_id, 0x1016, free, "u32", (m.master_id << 16) | int(round(m.timeout_ms)))
        self.consumer_subs[node_id] = free

    @contextlib.contextmanager
    def as_found(self, nodes: list[int]):
        """Inside: the application parameters the station changes at run time (profile velocity 0x6081, the
        reaction to a lost station 0x6007) are back to what each drive had, so a store (0x1010:03) keeps the
        calibration and nothing of the station's own; afterwards the station's reaction again."""
        for node_id in nodes:
            for (index, kind), value in self.found.get(node_id, {}).items():
                self.write_obj(node_id, index, 0, kind, value)
        try:
            yield
        finally:
            m = self.master
            for node_id in nodes:
                if node_id in self.consumer_subs and m is not None and m.reaction is not None:
                    with contextlib.suppress(StationError):
                        self.write_obj(node_id, 0x6007, 0, "i16", MasterLoss.REACTIONS[m.reaction])

    def per_node(self, nodes: list[int], fn: Callable[[int], object]) -> dict[int, object]:
        """``fn(node)`` for every node at once (each drive has its own SDO channel, so a configuration step costs
        one drive's answer times, not six); the first error, in node order, is raised after all finished."""
        if len(nodes) <= 1:
            return {n: fn(n) for n in nodes}
        if self._pool is None:
            self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=len(self.nodes),
                                                               thread_name_prefix="canopen-sdo")
        futures = {n: self._pool.submit(fn, n) for n in nodes}
        out, first = {}, None
        for n, f in futures.items():
            try:
                out[n] = f.result()
            except BaseException as e:  # noqa: BLE001 - re-raised below, after every drive's step ended
                first = first or e
        if first is not None:
            raise first
        return out

    def release_consumers(self) -> None:
        """Clean close: the drives stop watching the station (else a station that closed normally leaves every
        drive in its abort-connection reaction and an EMCY 0x8130 on the bus)."""
        for node_id, sub in list(self.consumer_subs.items()):
            with contextlib.suppress(Exception):
                self.write_obj(node_id, 0x1016, sub, "u32", 0)
            self.consumer_subs.pop(node_id, None)

    def _reload_soft_drives(self) -> None:
        """Torque limits below rated (0x6072, 0x60E0, 0x60E1 < 1000 per mille) at connect: a station that stopped
        while seating (killed, power lost) left the arm soft, and what the drive had before is known only to its
        store. NMT reset node reloads the stored parameters (CiA 301); a drive still below rated after it was
        configured so by its owner and is left alone. The drives are not enabled by then: their heartbeat
        consumer reacted to the lost station."""
        soft = [n for n in self.drives if any((v := self.read_opt(n, i, 0, "u16")) is not None and v < RATED_TORQUE
                                                for i in (0x6072, 0x60E0, 0x60E1))]
        if not soft:
            return
        log.warning("canopen: torque limits below rated on node(s) %s (left by a run that stopped while seating?): "
                    "NMT reset node to reload the drives' stored parameters", soft)
        for node_id in soft:
            node = self.drives[node_id]
            node.nmt.state = "RESET"
            try:
                node.nmt.wait_for_bootup(max(1.0, 5 * self.sdo_timeout))
            except canopen.nmt.NmtError:
                raise ConnectionLost(f"canopen node {node_id} on {self.where}: no boot-up after NMT reset "
                                     "node") from None
            node.nmt.state = "PRE-OPERATIONAL"

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
        for node_id in self.drives:
            if self.read_opt(node_id, CONTACT_WIRED, 0, "u8") == 1:
                return node_id
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
            self._retrying(node.id, lambda: (node.tpdo.save(), node.rpdo.save()))
        except canopen.SdoCommunicationError as e:
            raise ConnectionLost(f"canopen node {node.id}: PDO configuration failed: {e}") from None
        except canopen.SdoAbortedError as e:
            raise DeviceFault(f"canopen node {node.id} refused the PDO mapping: {e}", device=f"node {node.id}",
                              code=e.code) from None

    # ---- SDO (configuration only, never in the streaming cycle) ---------------------------------------------
    def _retrying(self, node_id: int, fn):
        """``fn()`` (a blocking python-canopen SDO transfer). The SDO timeout means the drive was silent: one that
        ran out while this process was not scheduled (the answer may sit unread in the socket), or while the drive
        kept sending its PDOs and heartbeats (alive, its answer lost or late), is asked again, for up to
        ``SDO_PATIENCE`` answer times in all. Raises the last SdoCommunicationError with the host's gap appended.
        A latched fault seen meanwhile (bus-off, error frames) is what is raised instead: it is the cause."""
        start = t0 = time.monotonic()
        tries = 0
        while True:
            try:
                return fn()
            except canopen.SdoCommunicationError as e:
                t1 = time.monotonic()
                self.faults.raise_if_latched()
                stalled = self.sched.stalled(t0, t1) > 0
                # its PDOs or heartbeat since the request, or an answer that was not this one's (a late answer to
                # an earlier request): the drive is there
                answered = not str(e).startswith("No SDO response")
                alive = answered or self._alive.get(node_id, 0.0) > t0
                if (stalled and tries < SDO_RETRIES_AFTER_STALL) or (
                        alive and t1 - start < SDO_PATIENCE * max(self.sdo_timeout, 0.1)):
                    tries += stalled
                    log.info("canopen node %d: no SDO answer while %s (%s): asked again", node_id,
                             "the station was not scheduled" if stalled else "the drive kept sending",
                             self.sched.note(t0, t1))
                    t0 = time.monotonic()
                    continue
                raise canopen.SdoCommunicationError(f"{e} ({self.sched.note(t0, t1)})") from None

    def _call(self, node_id: int, verb: str, index: int, sub: int | None, fn):
        """One SDO transfer's errors as the station's: no answer -> ConnectionLost, an abort -> DeviceFault."""
        obj = f"0x{index:04X}" if sub is None else f"0x{index:04X}:{sub:02X}"
        try:
            return self._retrying(node_id, fn)
        except canopen.SdoCommunicationError as e:
            raise ConnectionLost(f"canopen node {node_id} on {self.where} does not answer "
                                 f"(SDO {verb} {obj}: {e})") from None
        except canopen.SdoAbortedError as e:
            raise DeviceFault(f"canopen node {node_id}: SDO {verb} {obj} aborted: {e}", device=f"node {node_id}",
                              code=e.code) from None

    def sdo_read(self, node_id: int, index: int, sub: int = 0):
        node = self.drives[node_id]
        return self._call(node_id, "read", index, sub,
                          lambda: (node.sdo[index][sub] if sub else node.sdo[index]).raw)

    def read_obj(self, node_id: int, index: int, sub: int, kind: str) -> int:
        """A number by raw SDO upload, decoded as ``kind`` (``u8``..``i32``): objects outside the driver's
        dictionary and a vendor EDS alike."""
        node = self.drives[node_id]
        data = self._call(node_id, "read", index, sub, lambda: node.sdo.upload(index, sub))
        fmt = STRUCT[kind]
        size = struct.calcsize(fmt)
        return struct.unpack(fmt, bytes(data[:size]).ljust(size, b"\0"))[0]

    def read_opt(self, node_id: int, index: int, sub: int, kind: str) -> int | None:
        """``read_obj``, None when the drive does not have the object (SDO abort: an optional object)."""
        try:
            return self.read_obj(node_id, index, sub, kind)
        except DeviceFault:
            return None

    def sdo_read_u32(self, node_id: int, index: int, sub: int) -> int | None:
        return self.read_opt(node_id, index, sub, "u32")

    def write_obj(self, node_id: int, index: int, sub: int, kind: str, value: int,
                  timeout: float | None = None) -> None:
        """A number by raw SDO download (expedited), encoded as ``kind``."""
        node = self.drives[node_id]
        data = struct.pack(STRUCT[kind], int(value))
        self._with_timeout(node, timeout, lambda: self._call(
            node_id, "write", index, sub, lambda: node.sdo.download(index, sub, data)))

    def sdo_write(self, node_id: int, index: int, value, sub: int | None = None, timeout: float | None = None) -> None:
        """``timeout`` (s) replaces the URL's ``sdo_timeout_ms`` for this one transfer (the store command)."""
        node = self.drives[node_id]

        def write():
            if sub is None:
                node.sdo[index].raw = value
            else:
                node.sdo[index][sub].raw = value

        self._with_timeout(node, timeout, lambda: self._call(node_id, "write", index, sub, write))

    @staticmethod
    def _with_timeout(node, timeout: float | None, fn) -> None:
        usual = node.sdo.RESPONSE_TIMEOUT
        if timeout is not None:
            node.sdo.RESPONSE_TIMEOUT = max(timeout, usual)
        try:
            fn()
        finally:
            node.sdo.RESPONSE_TIMEOUT = usual

    def store_parameters(self, node_id: int) -> None:
        """0x1010:03 "save": the application parameters only (CiA 301: 0x6000-0x9FFF, where the home offset and
        homing result live), never "save all": that would make the station's runtime PDO layout and heartbeat
        settings the drive's power-up default. CiA 301 lets a drive answer only after its non-volatile memory is
        written, which takes a real drive hundreds of ms, so this transfer waits ``STORE_TIMEOUT_S`` at least."""
        self.sdo_write(node_id, 0x1010, SAVE, sub=STORE_APPLICATION, timeout=STORE_TIMEOUT_S)

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
        self._alive[node_id] = time.monotonic()
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
            self._cv.notify_all()

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
        periods, every node's newest reply after the call. A latched fault is raised instead. ``timeout`` is
        observed time (the station's own scheduling gaps are not the drives' silence)."""
        timeout = timeout or max(1.0, 20 * self.sync_period)
        deadline = Deadline(timeout, own_gap=max(0.05, 3 * self.sync_period))
        start = time.monotonic()
        with self._cv:
            s0 = self._seq
            snap = None
            expired = False
            while snap is None and self.faults.error is None:
                snap = self._complete_after(s0)
                if snap is None and time.monotonic() - start > 3 * self.sync_period:
                    snap = self._fresh_after(s0)
                if snap is None:
                    if deadline.expired():
                        expired = True
                        break
                    self._cv.wait(self.sync_period)
        if snap is None:
            self.faults.raise_if_latched()
            with self._cv:
                missing = [n for n in self.nodes if not any(k > s0 for k in self._history[n])]
            err = ConnectionLost(f"canopen {self.where}: no complete SYNC round within {timeout:.2f} s "
                                 f"(no TPDO from node(s) {missing or '?'}; {deadline.note()})")
            if expired:
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
        mode switch) and within one event period of now: the newest TPDO2 if it is such, else the next one
        (within 5 event periods, at least 0.2 s, of observed time)."""
        period = self.touch_ms / 1000.0
        with self._cv:
            last = self._contact
            now = time.monotonic()
            if last is None or last[0] <= self.changed_at or now - last[0] > 1.5 * period:
                floor = max(now, self.changed_at) if last is None or now - last[0] > 1.5 * period \
                    else self.changed_at
                limit = max(0.2, 5 * period)
                deadline = Deadline(limit, own_gap=max(0.05, 2 * period))
                while (self._contact is None or self._contact[0] <= floor) and self.faults.error is None:
                    if deadline.expired():
                        break
                    self._cv.wait(min(period, 0.02))
                last = self._contact
                if self.faults.error is None and (last is None or last[0] <= floor):
                    raise ConnectionLost(f"canopen node {self.contact_node}: no digital-input TPDO within "
                                         f"{limit * 1e3:.0f} ms ({deadline.note()})")
        self.faults.raise_if_latched()
        return struct.unpack_from("<I", last[1].ljust(4, b"\0"))[0]

    # ---- heartbeats ------------------------------------------------------------------------------------------
    def _on_heartbeat(self, node_id: int, state: int) -> None:
        self._last_hb[node_id] = self._alive[node_id] = time.monotonic()
        self.nmt_states[node_id] = state
        if (silence := self._hb_silence.get(node_id)) is not None:
            silence.reset()
        if state == 0 and not self.closing:
            self.faults.latch(ConnectionLost(f"canopen node {node_id} rebooted (boot-up message while running); "
                                             "reopen the robot"), fatal=True)

    def restart_preoperational(self) -> list[int]:
        """NMT start for the drives whose heartbeat says PRE-OPERATIONAL (a heartbeat event sent them there:
        CiA 301 0x1029 default; Lenze 8400 "changes from Operational to Pre-operational"); returns them."""
        again = [n for n, st in self.nmt_states.items() if st == 127]
        for node_id in again:
            self.drives[node_id].nmt.state = "OPERATIONAL"
        return again

    def silent_nodes(self) -> list[int]:
        """Nodes whose heartbeat is overdue now."""
        now = time.monotonic()
        return [n for n, t in self._last_hb.items() if now - t > self.hb_timeout]

    def _watchdog(self) -> None:
        step = min(0.05, self.heartbeat_ms / 4000.0)
        while not self._stop.wait(step):
            self.sched.turn()
            self._check_bus_state()
            for node_id, silence in list(self._hb_silence.items()):
                # a loaded station PC that did not run this thread (nor the receive thread) for a while has not
                # seen the heartbeats queued meanwhile: its own gap is not the drive's silence
                quiet = silence.tick()
                if quiet > self.hb_timeout:
                    self.faults.latch(ConnectionLost(
                        f"canopen node {node_id} on {self.where}: heartbeat lost ({quiet * 1e3:.0f} ms "
                        f"without one, expected every {self.heartbeat_ms} ms; {silence.note()}); robot stopped"))
                    if self.link_closed():
                        # python-can's socketcand client spins on a closed socket (select says readable,
                        # recv returns b""): stop its receive thread instead of burning a core until close()
                        self.faults.latch(ConnectionLost(f"socketcand server {self.host_addr} closed the "
                                                         "connection; reopen the robot"), fatal=True)
                        with contextlib.suppress(Exception):
                            self.network.notifier.stop(1.0)
                        return
                    break

    @property
    def host_addr(self) -> str:
        return f"{self.host}:{self.port}"

    def _check_bus_state(self) -> None:
        """python-can's own bus state (interfaces that report it: PCAN, IXXAT, ...; the others stay ACTIVE):
        ERROR is bus-off. socketcand never forwards error frames, so there only the heartbeat shows it."""
        bus = self.network.bus
        try:
            state = bus.state if bus is not None else None
        except Exception:  # noqa: BLE001 - an interface whose state query fails says nothing
            return
        if state == can.BusState.ERROR and self.faults.error is None:
            self.faults.latch(BusError(f"CAN bus-off on {self.where} (python-can bus state ERROR); check "
                                       "termination, bitrate and wiring"))

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
        """Stop SYNC, the watchdog and the station's heartbeat, disconnect (the drives were left safe by the
        robot)."""
        self.closing = True
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        if self.master_node is not None:
            with contextlib.suppress(Exception):
                self.master_node.nmt.stop_heartbeat()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        with contextlib.suppress(Exception):
            self.network.disconnect()
