"""CiA 402 robot over CANopen: one ``canopen.BaseNode402`` per joint, PDO streaming on a SYNC cycle.

Wire plan (configured by SDO at connect, then 0 SDOs per cycle):
  TPDO1 (SYNC, every cycle): statusword 0x6041, position actual 0x6064, mode display 0x6061
  TPDO2 (event timer, contact node only): digital inputs 0x60FD (bit 16 = the cell's contact input)
  RPDO1 (immediate): controlword 0x6040, target position 0x607A
  RPDO2 (immediate): mode 0x6060, profile velocity 0x6081, target torque 0x6071
A SYNC producer thread of the driver paces the TPDOs; a snapshot is one complete SYNC round.
Heartbeats (0x1017, consumer watchdog here), EMCY and CAN error frames latch typed errors and stop the
robot (quick stop on every drive).
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import struct
import threading
import time
from urllib.parse import urlsplit

import can
import canopen
import numpy as np
from station.drivers.canopen.od import CONTACT_WIRED, standard_od

from station.kinematics import Model, load_model
from station.robot.errors import (
    BusError,
    ConfigError,
    ConnectionLost,
    DeviceFault,
    LimitError,
    SafetyStop,
    StationError,
)
from station.robot.motion import MANUAL_TOOL_SPEED_CAP, check_joint_limits, jog_target, joint_speed_for_tool_cap
from station.robot.protocol import Identity, JointSnapshot, JointState, RobotStatus
from station.robot.registry import RobotURL, parse_ids

log = logging.getLogger("station.drivers.canopen")

CW_SHUTDOWN, CW_ENABLE, CW_QUICK_STOP = 0x06, 0x0F, 0x02
CW_NEW_SETPOINT, CW_IMMEDIATE, CW_HALT = 0x10, 0x20, 0x100
SW_TARGET_REACHED, SW_SETPOINT_ACK = 1 << 10, 1 << 12
MODE_PP, MODE_PT = 1, 4
COMPLIANT_TORQUE = 50  # per mille of rated torque while seating in a socket
SAVE = 0x65766173  # "save"
CAN_ERR_BUSOFF = 0x40
CONTACT_BIT = 16
STATES = (("NOT READY TO SWITCH ON", 0x4F, 0x00), ("SWITCH ON DISABLED", 0x4F, 0x40),
          ("READY TO SWITCH ON", 0x6F, 0x21), ("SWITCHED ON", 0x6F, 0x23), ("OPERATION ENABLED", 0x6F, 0x27),
          ("QUICK STOP ACTIVE", 0x6F, 0x07), ("FAULT REACTION ACTIVE", 0x4F, 0x0F), ("FAULT", 0x4F, 0x08))


def state_of(sw: int) -> str:
    for name, mask, bits in STATES:
        if sw & mask == bits:
            return name
    return "UNKNOWN"


class _BusWatch(can.Listener):
    """Error frames and receive errors on the raw bus (canopen's own listener ignores them)."""

    def __init__(self, robot: CanopenRobot) -> None:
        self.robot = robot
        self.error_frames = 0

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_error_frame:
            return
        self.error_frames += 1
        cls = msg.arbitration_id & 0x1FFFFFFF
        if cls & CAN_ERR_BUSOFF:
            self.robot._latch(BusError(f"CAN bus-off on {self.robot.where} (error frame class 0x{cls:X}); "
                                       "check termination, bitrate and wiring"))
        elif self.error_frames >= self.robot.error_frame_limit:
            self.robot._latch(BusError(f"CAN error frame on {self.robot.where} (class 0x{cls:X}, "
                                       f"{self.error_frames} so far): a frame was corrupted on the wire"))

    def on_error(self, exc: Exception) -> None:
        self.robot._latch(ConnectionLost(f"CAN interface {self.robot.where} failed: {exc}"))


class CanopenRobot:
    """A CiA 402 arm, one drive per joint (node order = joint order). Fulfils ``station.robot.Robot``."""

    def __init__(self, model: Model, nodes: list[int], *, interface: str, channel: str, host: str | None = None,
                 port: int | None = None, sync_period: float = 0.004, heartbeat_ms: int = 100,
                 touch_ms: int = 10, contact: int | None | str = "auto", eds: str | None = None,
                 serial: str | None = None, error_frame_limit: int = 1, url: str = "") -> None:
        if len(nodes) != model.n_joints:
            raise ConfigError(f"canopen: {len(nodes)} node ids {nodes} for model {model.name} with "
                              f"{model.n_joints} joints; give one node per joint (nodes=1-{model.n_joints})")
        for i, j in enumerate(model.joints):
            if j.encoder is None:
                raise ConfigError(f"canopen: joint {i + 1} ({j.name}) of model {model.name} has no encoder scaling")
        if not (0.0005 <= sync_period <= 1.0) or not (10 <= heartbeat_ms <= 10000):
            raise ConfigError(f"canopen: sync period {sync_period * 1e3:g} ms must be 0.5..1000 and heartbeat "
                              f"{heartbeat_ms} ms 10..10000")
        self.model = model
        self.nodes = list(nodes)
        self.interface, self.channel, self.host, self.port = interface, channel, host, port
        self.where = f"{interface} {host}:{port}/{channel}" if host else f"{interface} {channel}"
        self.sync_period = sync_period
        self.heartbeat_ms = heartbeat_ms
        self.hb_timeout = 3 * heartbeat_ms / 1000.0 + 0.2  # margin for a loaded host
        self.touch_ms = touch_ms
        self.error_frame_limit = max(1, error_frame_limit)
        self.url = url
        self._serial = serial
        self._eds = eds
        self._contact_arg = contact
        self.contact_node: int | None = None
        self._fault: StationError | None = None
        self._faults: list[str] = []
        self._fatal = False  # a fault enable() cannot clear (drive rebooted, server gone): reopen
        self._fault_lock = threading.Lock()
        self._cv = threading.Condition()
        self._seq = 0
        self._contact: tuple[float, bytes] | None = None  # (monotonic, data) of the last contact TPDO2
        self._history: dict[int, dict[int, tuple[int, int, int, float]]] = {n: {} for n in nodes}
        self._latest: dict[int, tuple[int, int, int, int, float]] = {}
        self._last_hb: dict[int, float] = {}
        self._tx_lock = threading.RLock()
        self._stop = threading.Event()
        self._interrupt = threading.Event()  # set by stop() from any thread: ends a waited move
        self._threads: list[threading.Thread] = []
        self._compliant = False
        self._cmd_seq = 0  # SYNC count when the last RPDO was sent: rounds after it reflect every command
        self._changed_at = 0.0  # monotonic: last RPDO sent or command confirmed (a touch reading must be newer)
        self._identity: Identity | None = None
        self._closed = False
        self.sync_frames = 0
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # bounds how long close() waits for the bus thread
        self._watch = _BusWatch(self)
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_url(cls, url: RobotURL, **kw) -> CanopenRobot:
        """``canopen+virtual://CHANNEL?nodes=1-6&model=arm6`` or
        ``canopen+socketcand://HOST:PORT?channel=can0&nodes=1-6&model=arm6``; optional ``sync_ms`` (4),
        ``heartbeat_ms`` (100), ``touch_ms`` (10), ``contact`` (node id | none | auto), ``eds`` (file),
        ``serial``, ``error_frames`` (error frames tolerated before BusError, 1)."""
        q = url.query
        known = {"nodes", "model", "channel", "sync_ms", "heartbeat_ms", "touch_ms", "contact", "eds", "serial",
                 "error_frames"}
        unknown = sorted(set(q) - known)
        if unknown:
            raise ConfigError(f"robot URL {url.raw!r}: unknown parameter(s) {', '.join(unknown)}; "
                              f"known: {', '.join(sorted(known))}")
        if "model" not in q:
            raise ConfigError(f"robot URL {url.raw!r}: add model=NAME (e.g. model=arm6)")
        try:
            model = load_model(q["model"])
        except (OSError, ValueError, KeyError) as e:
            raise ConfigError(f"robot URL {url.raw!r}: model {q['model']!r}: {e}") from None
        nodes = parse_ids(q.get("nodes", f"1-{model.n_joints}"))
        try:
            sync_ms = float(q.get("sync_ms", 4))
            hb = int(q.get("heartbeat_ms", 100))
            touch = int(q.get("touch_ms", 10))
            frames = int(q.get("error_frames", 1))
        except ValueError:
            raise ConfigError(f"robot URL {url.raw!r}: sync_ms, heartbeat_ms, touch_ms, error_frames are "
                              "numbers") from None
        contact: int | None | str = q.get("contact", "auto")
        if contact not in ("auto", "none"):
            try:
                contact = int(contact)
            except ValueError:
                raise ConfigError(f"robot URL {url.raw!r}: contact must be a node id, 'none' or 'auto'") from None
        contact = None if contact == "none" else contact
        common = dict(sync_period=sync_ms / 1000.0, heartbeat_ms=hb, touch_ms=touch, contact=contact,
                      eds=q.get("eds"), serial=q.get("serial"), error_frame_limit=frames, url=url.raw)
        common.update(kw)
        if url.scheme == "canopen+virtual":
            # the netloc keeps the channel's case (RobotURL.host is lower-cased by urlsplit)
            channel = q.get("channel") or urlsplit(url.raw).netloc or url.path.strip("/")
            if not channel:
                raise ConfigError(f"robot URL {url.raw!r}: give the virtual channel, canopen+virtual://chan0?...")
            return cls(model, nodes, interface="virtual", channel=channel, **common)
        if url.scheme == "canopen+socketcand":
            if not url.host or not url.port:
                raise ConfigError(f"robot URL {url.raw!r}: give host:port of the socketcand server")
            return cls(model, nodes, interface="socketcand", channel=q.get("channel", "can0"), host=url.host,
                       port=url.port, **common)
        raise ConfigError(f"robot URL {url.raw!r}: scheme {url.scheme!r} is not a CANopen scheme")

    def _open_bus(self) -> can.BusABC:
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

    def _connect(self) -> None:
        bus = self._open_bus()
        self.network.bus = bus
        self.network.listeners.append(self._watch)
        self.network.connect()
        self.drives: dict[int, canopen.BaseNode402] = {}
        for node_id in self.nodes:
            od = canopen.import_od(self._eds, node_id) if self._eds else standard_od(node_id)
            node = canopen.BaseNode402(node_id, od)
            self.network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 0.3
            self.drives[node_id] = node
        for node_id, node in self.drives.items():
            dtype = self._first_contact(node)
            if dtype & 0xFFFF != 402:
                raise ConfigError(f"canopen node {node_id} on {self.where} is not a CiA 402 drive "
                                  f"(device type 0x{dtype:08X})")
            node.nmt.state = "PRE-OPERATIONAL"
        self.contact_node = self._find_contact()
        for node_id, node in self.drives.items():
            self._configure_pdos(node, node_id == self.contact_node)
            node.setup_402_state_machine(read_pdos=False)
            node.tpdo[1].add_callback(lambda m, n=node_id: self._on_tpdo1(n, m))
            if node_id == self.contact_node:
                node.tpdo[2].add_callback(self._on_tpdo2)
            node.emcy.add_callback(lambda e, n=node_id: self._on_emcy(n, e))
            node.nmt.add_heartbeat_callback(lambda s, n=node_id: self._on_heartbeat(n, s))
            self._sdo_write(node, 0x1017, self.heartbeat_ms)
            self._last_hb[node_id] = time.monotonic()
        for node in self.drives.values():
            node.nmt.state = "OPERATIONAL"
        for target, name in ((self._sync_loop, "sync"), (self._watchdog, "watchdog")):
            t = threading.Thread(target=target, name=f"canopen-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        snap = self._round(timeout=max(1.0, 20 * self.sync_period))
        # hold position: the RPDOs carry the present position and profile position mode from now on
        for node_id, node in self.drives.items():
            node.rpdo[1][0x607A].raw = snap[node_id][1]
            self._send_rpdo2(node, MODE_PP, 0, 0)
        self._wait_mode(MODE_PP)

    def _first_contact(self, node, attempts: int = 3) -> int:
        """Device type 0x1000, asked up to ``attempts`` times: a drive still booting (power-up, or NMT reset just
        before the station connects) ignores SDO requests until its boot-up message."""
        for attempt in range(attempts):
            try:
                return self._sdo_read(node, 0x1000)
            except ConnectionLost:
                if attempt == attempts - 1:
                    raise
        raise AssertionError("unreachable")

    def _find_contact(self) -> int | None:
        if self._contact_arg != "auto":
            if self._contact_arg is not None and self._contact_arg not in self.drives:
                raise ConfigError(f"canopen: contact node {self._contact_arg} is not one of {self.nodes}")
            return self._contact_arg
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

    # ---- SDO helpers (configuration only, never in the streaming cycle) ------------------------
    def _sdo_read(self, node, index: int, sub: int = 0):
        try:
            return (node.sdo[index][sub] if sub else node.sdo[index]).raw
        except canopen.SdoCommunicationError as e:
            raise ConnectionLost(f"canopen node {node.id} on {self.where} does not answer "
                                 f"(SDO 0x{index:04X}:{sub:02X}: {e})") from None
        except canopen.SdoAbortedError as e:
            raise DeviceFault(f"canopen node {node.id}: reading 0x{index:04X}:{sub:02X} aborted: {e}",
                              device=f"node {node.id}", code=e.code) from None

    def _sdo_write(self, node, index: int, value, sub: int | None = None) -> None:
        try:
            if sub is None:
                node.sdo[index].raw = value
            else:
                node.sdo[index][sub].raw = value
        except canopen.SdoCommunicationError as e:
            raise ConnectionLost(f"canopen node {node.id} on {self.where} does not answer "
                                 f"(SDO write 0x{index:04X}: {e})") from None
        except canopen.SdoAbortedError as e:
            raise DeviceFault(f"canopen node {node.id}: writing 0x{index:04X} aborted: {e}",
                              device=f"node {node.id}", code=e.code) from None

    # ---- streaming: SYNC producer, TPDO rounds ------------------------------------------------
    def _sync_loop(self) -> None:
        t_next = time.monotonic()
        while not self._stop.is_set():
            with self._cv:
                self._seq += 1
            try:
                self.network.send_message(0x80, b"")
                self.sync_frames += 1
            except (can.CanError, OSError, AttributeError) as e:
                self._latch(ConnectionLost(f"cannot send SYNC on {self.where}: {e}"))
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

    def _complete_after(self, s0: int):
        seqs = None
        for hist in self._history.values():
            s = {k for k in hist if k > s0}
            seqs = s if seqs is None else seqs & s
            if not seqs:
                return None
        best = max(seqs)
        return {n: self._history[n][best] for n in self.nodes}

    def _fresh_after(self, s0: int):
        """Latest TPDO of every node received after SYNC ``s0`` (rounds not aligned: a loaded bus/host)."""
        out = {}
        for n, hist in self._history.items():
            newer = [k for k in hist if k > s0]
            if not newer:
                return None
            out[n] = hist[max(newer)]
        return out

    def _round(self, timeout: float | None = None) -> dict[int, tuple[int, int, int, float]]:
        """A complete SYNC round started after this call: {node: (statusword, counts, mode, t)}. If the
        replies of one SYNC do not line up within 3 periods, every node's newest reply after the call."""
        timeout = timeout or max(1.0, 20 * self.sync_period)
        start = time.monotonic()
        with self._cv:
            s0 = self._seq
            snap = None
            while snap is None and self._fault is None:
                snap = self._complete_after(s0)
                waited = time.monotonic() - start
                if snap is None and waited > 3 * self.sync_period:
                    snap = self._fresh_after(s0)
                if snap is None:
                    if waited > timeout:
                        break
                    self._cv.wait(min(self.sync_period, timeout - waited + 1e-3))
        if snap is None:
            self._raise_fault()
            with self._cv:
                missing = [n for n in self.nodes if not any(k > s0 for k in self._history[n])]
            err = ConnectionLost(f"canopen {self.where}: no complete SYNC round within {timeout:.2f} s "
                                 f"(no TPDO from node(s) {missing or '?'})")
            self._latch(err)
            raise err
        return snap

    def _recent(self) -> dict[int, tuple[int, int, int, float]]:
        """The newest complete SYNC round if it already reflects every command sent so far and is at most one
        cycle old (the drives' state and position as of now, to within one cycle); otherwise the next round."""
        with self._cv:
            floor = max(self._cmd_seq, self._seq - 2)
            snap = self._complete_after(floor)
        return snap if snap is not None else self._round()

    # ---- faults -------------------------------------------------------------------------------
    def _latch(self, err: StationError) -> None:
        with self._fault_lock:
            first = self._fault is None
            if first:
                self._fault = err
            self._faults.append(str(err))
        if first:
            log.warning("canopen: %s", err)
            self._quick_stop_all()
            with self._cv:
                self._cv.notify_all()

    def _raise_fault(self) -> None:
        if self._fault is not None:
            raise self._fault

    def _quick_stop_all(self) -> None:
        """Quick stop every drive by RPDO (no SDO: safe from the bus thread and with dead nodes)."""
        for node in getattr(self, "drives", {}).values():
            with contextlib.suppress(Exception):
                self._send_rpdo1(node, CW_QUICK_STOP)

    def _on_emcy(self, node_id: int, e) -> None:
        if e.code & 0xFF00 == 0:
            return  # error reset
        joint = self.model.joints[self.nodes.index(node_id)].name
        self._latch(DeviceFault(f"canopen node {node_id} (joint {joint}) EMCY 0x{e.code:04X} "
                                f"{e.get_desc() or 'device error'} (error register 0x{e.register:02X}); "
                                "robot stopped", device=f"node {node_id}", code=e.code))

    def _on_heartbeat(self, node_id: int, state: int) -> None:
        self._last_hb[node_id] = time.monotonic()
        if state == 0 and not self._closed:
            self._fatal = True
            self._latch(ConnectionLost(f"canopen node {node_id} rebooted (boot-up message while running); "
                                       "reopen the robot"))

    def _watchdog(self) -> None:
        step = min(0.05, self.heartbeat_ms / 4000.0)
        while not self._stop.wait(step):
            now = time.monotonic()
            for node_id, t in list(self._last_hb.items()):
                if now - t > self.hb_timeout:
                    self._latch(ConnectionLost(
                        f"canopen node {node_id} on {self.where}: heartbeat lost ({(now - t) * 1e3:.0f} ms "
                        f"without one, expected every {self.heartbeat_ms} ms); robot stopped"))
                    if self._server_closed():
                        self._fatal = True
                        # python-can's socketcand client spins on a closed socket (select says readable,
                        # recv returns b""): stop its receive thread instead of burning a core until close()
                        self._latch(ConnectionLost(f"socketcand server {self.host}:{self.port} closed the "
                                                   "connection; reopen the robot"))
                        with contextlib.suppress(Exception):
                            self.network.notifier.stop(1.0)
                        return
                    break

    def _server_closed(self) -> bool:
        """True if the socketcand TCP connection reached end-of-file."""
        sock = getattr(self.network.bus, "_SocketCanDaemonBus__socket", None)
        if self.interface != "socketcand" or sock is None:
            return False
        try:
            return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            return False
        except OSError:
            return True

    # ---- RPDO helpers -------------------------------------------------------------------------
    def _send_rpdo1(self, node, cw: int, target: int | None = None) -> None:
        with self._tx_lock:
            self._cmd_seq, self._changed_at = self._seq, time.monotonic()
            m = node.rpdo[1]
            if target is not None:
                m[0x607A].raw = int(target)
            m[0x6040].raw = cw
            m.transmit()

    def _send_rpdo2(self, node, mode: int, velocity: int, torque: int) -> None:
        with self._tx_lock:
            self._cmd_seq, self._changed_at = self._seq, time.monotonic()
            m = node.rpdo[2]
            m[0x6060].raw = mode
            m[0x6081].raw = max(0, min(int(velocity), 0xFFFFFFFF))
            m[0x6071].raw = int(torque)
            m.transmit()

    def _wait(self, what: str, cond, timeout: float, interruptible: bool = False) -> dict:
        end = time.monotonic() + timeout
        while True:
            if interruptible and self._interrupt.is_set():
                raise SafetyStop(f"canopen {self.where}: move interrupted by stop(); the arm holds where it stopped")
            snap = self._round()
            if cond(snap):
                self._changed_at = time.monotonic()
                return snap
            if time.monotonic() > end:
                self.stop()  # whatever did not happen, nothing keeps moving
                bad = [n for n in self.nodes if not cond({n: snap[n]})]
                raise DeviceFault(f"canopen {self.where}: {what} not confirmed within {timeout:.1f} s "
                                  f"(node(s) {bad})", device=f"node {bad[0]}" if bad else None)

    def _wait_mode(self, mode: int) -> dict:
        return self._wait(f"mode of operation {mode}", lambda s: all(v[2] == mode for v in s.values()), 1.0)

    # ---- Robot protocol -----------------------------------------------------------------------
    def identity(self) -> Identity:
        if self._identity is None:
            devices = []
            for i, (node_id, node) in enumerate(self.drives.items()):
                ident = {k: self._sdo_read(node, 0x1018, s) for s, k in
                         ((1, "vendor_id"), (2, "product_code"), (3, "revision"), (4, "serial"))}
                devices.append({"node": node_id, "joint": self.model.joints[i].name,
                                "name": self._sdo_read(node, 0x1008), "hardware": self._sdo_read(node, 0x1009),
                                "firmware": self._sdo_read(node, 0x100A), **ident})
            first = devices[0]
            serial = self._serial or f"{first['vendor_id']:08X}-{first['serial']:08X}"
            self._identity = Identity(vendor=f"{first['name']} (CiA vendor 0x{first['vendor_id']:08X})",
                                      model=self.model.name, serial=serial, firmware=first["firmware"],
                                      devices=tuple(devices), url=self.url,
                                      serial_source="url" if self._serial else "derived")
        return self._identity

    def _to_q(self, counts) -> np.ndarray:
        return np.array([float(j.encoder.to_si(c)) for j, c in zip(self.model.joints, counts, strict=True)])

    def joint_positions(self) -> JointSnapshot:
        self._raise_fault()
        snap = self._round()
        counts = tuple(int(snap[n][1]) for n in self.nodes)
        t = max(v[3] for v in snap.values())
        return JointSnapshot(q=self._to_q(counts), raw=counts, raw_unit="count", t=t)

    def _require_enabled(self, snap) -> None:
        off = [n for n in self.nodes if state_of(snap[n][0]) != "OPERATION ENABLED"]
        if off:
            raise SafetyStop(f"canopen: drive(s) {off} not enabled "
                             f"({', '.join(sorted({state_of(snap[n][0]) for n in off}))}); call enable()")

    def move_joints(self, q: np.ndarray, speed: float | None = None, wait: bool = True) -> None:
        self._raise_fault()
        target = check_joint_limits(self.model, q, "move_joints")
        vmax = self.model.max_velocity
        if speed is not None and not (math.isfinite(speed) and speed > 0):
            raise LimitError(f"move_joints: speed must be a positive number of rad/s, got {speed!r}; nothing sent")
        limit = vmax * 0.25 if speed is None else np.minimum(speed, vmax)  # default 25 % of each joint's max
        if self._compliant:
            raise SafetyStop("canopen: robot is compliant (set_compliant(False) first); nothing sent")
        self._interrupt.clear()
        # state and start position from the newest round (<= 1 cycle old): the profile velocities only scale
        # the joints to arrive together, each stays <= its limit whatever the start, so a cycle-old start is safe
        snap = self._recent()
        self._require_enabled(snap)
        q0 = self._to_q([snap[n][1] for n in self.nodes])
        dq = np.abs(target - q0)
        duration = float(np.max(dq / limit))
        if duration <= 0:
            return
        for i, node in enumerate(self.drives.values()):
            enc = self.model.joints[i].encoder
            per_unit = enc.counts_per_unit * enc.gear
            v = max(1, int(math.ceil(dq[i] / duration * per_unit)))  # synchronised: all joints arrive together
            self._send_rpdo2(node, MODE_PP, v, 0)
            counts = int(round(float(enc.to_counts(target[i]))))
            self._send_rpdo1(node, CW_ENABLE | CW_NEW_SETPOINT | CW_IMMEDIATE, counts)
        self._wait("set-point acknowledge", lambda s: all(v[0] & SW_SETPOINT_ACK for v in s.values()), 1.0)
        for node in self.drives.values():
            self._send_rpdo1(node, CW_ENABLE)
        if wait:
            self._wait("target reached", lambda s: all(v[0] & SW_TARGET_REACHED and not v[0] & SW_SETPOINT_ACK
                                                       for v in s.values()), 2.0 * duration + 2.0,
                       interruptible=True)
            self._raise_fault()

    def jog(self, mode: str, axis: int, step: float, speed: float | None = None) -> None:
        self._raise_fault()
        if not math.isfinite(step):
            raise LimitError(f"jog: step must be finite, got {step!r}; nothing sent")
        q0 = self.joint_positions().q
        target = jog_target(self.model, q0, mode, axis, step)
        if mode == "cartesian":
            if speed is not None and not (math.isfinite(speed) and 0 < speed <= MANUAL_TOOL_SPEED_CAP):
                raise LimitError(f"jog: tool speed {speed!r} m/s outside (0, {MANUAL_TOOL_SPEED_CAP}] m/s; "
                                 "nothing sent")
            lead = joint_speed_for_tool_cap(self.model, q0, target, None,
                                            cap=speed or MANUAL_TOOL_SPEED_CAP / 2)
        else:
            if speed is not None and not (math.isfinite(speed) and speed > 0):
                raise LimitError(f"jog: joint speed must be a positive number of rad/s, got {speed!r}")
            lead = joint_speed_for_tool_cap(self.model, q0, target, speed if speed else 0.1)
        self.move_joints(target, speed=lead, wait=True)

    def stop(self) -> None:
        """Halt every drive (controlword bit 8): decelerate and hold, drives stay enabled; a waited move in
        another thread ends with SafetyStop."""
        self._interrupt.set()
        for node in getattr(self, "drives", {}).values():
            with contextlib.suppress(Exception):
                self._send_rpdo1(node, CW_ENABLE | CW_HALT)

    def enable(self) -> None:
        """Fault reset where needed, then every drive to OPERATION ENABLED holding its present position.
        Clears a latched fault only once the cause is gone (heartbeats back, bus up)."""
        if isinstance(self._fault, ConnectionLost):
            now = time.monotonic()
            dead = [n for n, t in self._last_hb.items() if now - t > self.hb_timeout]
            if dead or self._fatal:
                raise self._fault
        with self._fault_lock:
            self._fault = None
            self._faults.clear()
        for node in self.drives.values():
            node.emcy.reset()
        snap = self._round()
        for node_id, node in self.drives.items():
            node.rpdo[1][0x607A].raw = snap[node_id][1]
            self._send_rpdo2(node, MODE_PP, 0, 0)
        self._compliant = False
        self._enable_all(snap)
        self._raise_fault()

    def _enable_all(self, snap, timeout: float = 1.0) -> None:
        """CiA 402 power state machine of every drive at once: each round, every drive not yet OPERATION
        ENABLED gets the controlword of its next transition (fault reset 2-edge, shutdown, switch on, enable
        operation), and the next SYNC round confirms it; a drive needs up to 4 rounds, all drives together too
        (one drive after another waited up to 3 rounds each)."""
        step = {"FAULT": 0x80, "SWITCH ON DISABLED": CW_SHUTDOWN, "READY TO SWITCH ON": 0x07,
                "SWITCHED ON": CW_ENABLE, "QUICK STOP ACTIVE": CW_ENABLE}
        last: dict[int, int] = {}
        end = time.monotonic() + timeout
        while True:
            pending = {n: state_of(snap[n][0]) for n in self.nodes if state_of(snap[n][0]) != "OPERATION ENABLED"}
            if not pending:
                self._changed_at = time.monotonic()
                return
            if time.monotonic() > end:
                n, st = next(iter(pending.items()))
                err = DeviceFault(f"canopen node {n}: cannot enable (stays in {st} after {timeout:g} s; "
                                  f"node(s) {sorted(pending)} not enabled)", device=f"node {n}")
                self._latch(err)
                raise err
            for n, st in pending.items():
                cw = step.get(st)
                if cw is None:
                    continue  # NOT READY / FAULT REACTION ACTIVE pass by themselves
                if cw == 0x80 and last.get(n) == 0x80:
                    cw = 0x00  # the fault reset acts on a rising edge: drop the bit, set it again next round
                last[n] = cw
                self._send_rpdo1(self.drives[n], cw)
            snap = self._round()

    def disable(self) -> None:
        self.stop()
        for node in self.drives.values():
            with contextlib.suppress(Exception):
                self._send_rpdo1(node, CW_SHUTDOWN)
        self._compliant = False

    def status(self) -> RobotStatus:
        with self._cv:
            latest = dict(self._latest)
        joints, faults = [], list(self._faults)
        for i, node_id in enumerate(self.nodes):
            name = self.model.joints[i].name
            sw = latest.get(node_id, (0, 0))[1]
            st = state_of(sw)
            fault = None
            if st in ("FAULT", "FAULT REACTION ACTIVE"):
                active = self.drives[node_id].emcy.active
                fault = f"EMCY 0x{active[-1].code:04X}" if active else "FAULT"
                faults.append(f"node {node_id} ({name}): {fault}")
            enabled = st == "OPERATION ENABLED"
            joints.append(JointState(name, enabled, enabled and not sw & SW_TARGET_REACHED, fault))
        return RobotStatus(enabled=all(j.enabled for j in joints), moving=any(j.moving for j in joints),
                           faults=tuple(dict.fromkeys(faults)), compliant=self._compliant, joints=tuple(joints))

    def touch(self) -> bool | None:
        if self.contact_node is None:
            return None
        self._raise_fault()
        # the input as the drive sampled it after the last command took effect (a move that ended, a mode
        # switch) and within one event period of now: the newest TPDO2 if it is such, else the next one
        with self._cv:
            last = self._contact
        now = time.monotonic()
        if last is None or last[0] <= self._changed_at or now - last[0] > 1.5 * self.touch_ms / 1000.0:
            pdo = self.drives[self.contact_node].tpdo[2]
            if pdo.wait_for_reception(timeout=max(0.2, 5 * self.touch_ms / 1000.0)) is None:
                self._raise_fault()
                raise ConnectionLost(f"canopen node {self.contact_node}: no digital-input TPDO within "
                                     f"{5 * self.touch_ms} ms")
            last = (now, bytes(pdo.data))  # canopen stores the data before it runs our callback
        value = struct.unpack_from("<I", last[1].ljust(4, b"\0"))[0]
        return bool(value >> CONTACT_BIT & 1)

    def set_compliant(self, on: bool) -> None:
        """On: profile torque mode (0x6060 = 4) with a small target torque (0x6071 = 5 % rated) on every
        drive, so the arm yields and a socket can seat the tip. Off: hold the present position in profile
        position mode."""
        self._raise_fault()
        self._require_enabled(self._recent())
        if on:
            for node in self.drives.values():
                self._send_rpdo2(node, MODE_PT, 0, COMPLIANT_TORQUE)
            self._wait_mode(MODE_PT)  # confirmed: a lost frame would leave the arm stiff while seating
            self._compliant = True
            return
        for node in self.drives.values():
            self._send_rpdo2(node, MODE_PP, 0, 0)
        # confirmed: a lost frame would leave a joint limp; the drive holds the position it had at the switch,
        # and the confirming round carries it (no extra round to read it)
        snap = self._wait_mode(MODE_PP)
        for node_id, node in self.drives.items():
            self._send_rpdo1(node, CW_ENABLE, snap[node_id][1])
        self._compliant = False

    def read_calibration(self) -> dict[str, float]:
        """Home offsets 0x607C in SI: ``offset.jN = direction * counts / (counts_per_unit * gear)``."""
        out = {}
        for i, node in enumerate(self.drives.values()):
            enc = self.model.joints[i].encoder
            counts = int(self._sdo_read(node, 0x607C))
            out[f"offset.j{i + 1}"] = enc.direction * counts / (enc.counts_per_unit * enc.gear)
        return out

    def write_calibration(self, values: dict[str, float]) -> None:
        """Write absolute home offsets (SI) to 0x607C, store them (0x1010 "save"), read them back."""
        plan = {}
        for name, value in values.items():
            idx = None
            if name.startswith("offset.j") and name[8:].isdigit():
                idx = int(name[8:]) - 1
            if idx is None or not 0 <= idx < self.model.n_joints:
                raise ConfigError(f"write_calibration: {name!r} is not an offset of this robot "
                                  f"(offset.j1..offset.j{self.model.n_joints})")
            if not math.isfinite(value):
                raise ConfigError(f"write_calibration: {name} = {value!r} is not finite")
            enc = self.model.joints[idx].encoder
            counts = int(round(value * enc.counts_per_unit * enc.gear * enc.direction))
            if not -(1 << 31) <= counts < (1 << 31):
                raise ConfigError(f"write_calibration: {name} = {value:g} does not fit the drive's home offset")
            plan[self.nodes[idx]] = (name, counts)
        for node_id, (_name, counts) in plan.items():
            self._sdo_write(self.drives[node_id], 0x607C, counts)
        for node_id in plan:
            self._sdo_write(self.drives[node_id], 0x1010, SAVE, sub=1)
        for node_id, (name, counts) in plan.items():
            back = int(self._sdo_read(self.drives[node_id], 0x607C))
            if back != counts:
                raise DeviceFault(f"write_calibration: node {node_id} ({name}) reads back home offset {back} "
                                  f"counts, wrote {counts}", device=f"node {node_id}")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if getattr(self, "drives", None) and self._fault is None:
            self.stop()
            with contextlib.suppress(Exception):
                time.sleep(2 * self.sync_period)
                for node in self.drives.values():
                    self._send_rpdo1(node, CW_SHUTDOWN)
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        with contextlib.suppress(Exception):
            self.network.disconnect()

    def __enter__(self) -> CanopenRobot:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

