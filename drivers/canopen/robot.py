"""``CanopenRobot``: the Robot protocol over CiA 402 drives, one per joint (node order = joint order).

The wire (bus, PDO plan, SYNC rounds, heartbeats, SDO/RPDO helpers) is ``station.drivers.canopen.bus``; this
layer is the CiA 402 side: the power state machine of all drives at once, profile position moves in the drives'
own units (``units``), seating compliance by reduced torque limits, zero offsets set by homing
(``calibration``), and what a latched fault means for the robot (quick stop on every drive)."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time

import numpy as np
from station.drivers.canopen.bus import CanopenBus, MasterLoss, Round
from station.drivers.canopen.calibration import ZeroSetter, read_zero
from station.drivers.canopen.cia402 import (
    CONTACT_BIT,
    CW_ENABLE,
    CW_HALT,
    CW_IMMEDIATE,
    CW_NEW_SETPOINT,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    ENABLED,
    FAULTED,
    MODE_HM,
    MODE_PP,
    SUPPORTS_HOMING,
    SW_HOMING_ATTAINED,
    SW_HOMING_ERROR,
    SW_SETPOINT_ACK,
    SW_TARGET_REACHED,
    next_controlword,
    state_of,
)
from station.drivers.canopen.faults import FaultLatch
from station.drivers.canopen.interfaces import INTERFACES
from station.drivers.canopen.timing import Deadline
from station.drivers.canopen.units import read_units

from station.kinematics import Model
from station.robot.base import CHAIN_OPTIONS, RobotBase
from station.robot.errors import ConfigError, ConnectionLost, DeviceFault, SafetyStop, StationError
from station.robot.motion import MANUAL_TOOL_SPEED_CAP
from station.robot.protocol import Identity, JointSnapshot, JointState, RobotStatus
from station.robot.url import REQUIRED, Option, Options, RobotURL, either, id_list, integer, number, text

log = logging.getLogger("station.drivers.canopen")
CW_DISABLE_VOLTAGE = 0x0000  # CiA 402: any state -> SWITCH ON DISABLED (power stage off, holding brake engaged)
SEAT_RELATIVE = 0.1  # share of the holding torque added to the seating limits, beyond seat_margin


def _holds(cond, snap: Round, node: int) -> bool:
    """``cond`` evaluated on one node's entry (conditions over all nodes, or over a subset)."""
    try:
        return bool(cond({node: snap[node]}))
    except KeyError:
        return True  # a condition about other nodes only


class CanopenRobot(RobotBase):
    """A CiA 402 arm, one drive per joint, on any CAN adapter python-can speaks:
    ``canopen+<interface>://<channel>?...`` (socketcan, pcan, kvaser, ixxat, slcan, virtual) or
    ``canopen+socketcand://HOST:PORT?channel=can0&...``."""

    options = Options(
        Option("model", text(), REQUIRED, "kinematic model (built-in name or model file); gives counts/rev, gear, "
               "direction, limits"),
        Option("nodes", id_list(), None, "node ids in joint order (`1-6`, `11,12,14`)", default_doc="`1-n`"),
        Option("channel", text(), None, "socketcand bus name (socketcand only; for the other interfaces the host "
               "part or path is the channel)", default_doc="`can0`"),
        Option("bitrate", integer(10000, 1000000), None, "CAN bitrate (bit/s) the adapter is opened with "
               "(pcan, kvaser, ixxat, slcan; SocketCAN's is set with ip link)",
               default_doc="python-can's (its configuration, else 500000)"),
        Option("sync_ms", number(0.5, 1000, unit="ms"), 4.0, "SYNC period of the driver's SYNC producer = "
               "streaming cycle"),
        Option("heartbeat_ms", integer(10, 10000), 100, "0x1017 heartbeat time written to each drive"),
        Option("heartbeat_timeout_ms", number(20, 60000, unit="ms"), None, "heartbeat consumer time: a drive "
               "silent this long is lost (ConnectionLost, robot stopped); must exceed `heartbeat_ms`",
               default_doc="3 x `heartbeat_ms` + 500 (= 800)"),
        Option("master_id", integer(1, 127), 127, "node id of the station's own heartbeat (0x1017 of its "
               "python-canopen LocalNode); must differ from the drives'"),
        Option("master_heartbeat_ms", integer(10, 10000), 100, "the station's heartbeat period"),
        Option("master_timeout_ms", number(20, 65535, unit="ms"), None, "consumer time written to each drive "
               "(0x1016): a drive that hears no station heartbeat this long reacts (`on_master_loss`); must exceed "
               "`master_heartbeat_ms`", default_doc="3 x `master_heartbeat_ms` + 500 (= 800)"),
        Option("on_master_loss", either("quick_stop", "fault", "disable", none=("none",)), "quick_stop",
               "each drive's reaction when the station's heartbeat stops (0x6007: quick stop, fault, disable "
               "voltage); `none`: the drives are not told to watch the station (a killed station leaves them "
               "moving: only for drives guarded otherwise)"),
        Option("encoder", either("referenced", "absolute"), "referenced", "`referenced`: every drive must report "
               "its position referenced (homing attained, checked in homing mode at connect) before anything "
               "moves; `absolute`: the encoders are multi-turn absolute (or battery-buffered), 0x6064 is trusted "
               "at power-up"),
        Option("seat_margin", integer(1, 1000), 30, "per mille of rated torque the seating limits leave beyond "
               "the torque holding each joint takes (0x6077 read while holding; and at least 10 % of it)"),
        Option("sdo_timeout_ms", number(10, 60000, unit="ms"), 300.0, "SDO answer time (configuration, "
               "identity, write-back) of observed time; no answer is `ConnectionLost`. The store command (0x1010 "
               "\"save\") waits at least 3 s: a drive answers it after writing its flash"),
        Option("touch_ms", integer(1, 65535), 10, "event timer of the contact-input TPDO (ms)"),
        Option("contact", either("auto", none=("none",), otherwise=integer(1, 127)), "auto",
               "node with the contact input; `auto` reads 0x2000 on each node, `none` = no input"),
        Option("eds", text(), None, "vendor EDS file instead of the driver's built-in standard CiA 301/402 "
               "dictionary", default_doc="built-in"),
        Option("serial", text(), None, "robot serial for records (default `VENDORID-SERIAL` of the first drive)",
               default_doc="from 0x1018"),
        Option("error_frames", integer(1), 1, "CAN error frames tolerated within any 1 s (an isolated one is normal: "
               "the damaged frame is retransmitted); one more within that second is `BusError` (bus-off is always "
               "immediate; socketcand never forwards error frames)"),
        *CHAIN_OPTIONS,
    )

    def __init__(self, model: Model, nodes: list[int], *, interface: str, channel: str, host: str | None = None,
                 port: int | None = None, sync_period: float = 0.004, heartbeat_ms: int = 100,
                 touch_ms: int = 10, contact: int | None | str = "auto", eds: str | None = None,
                 serial: str | None = None, error_frame_limit: int = 1, heartbeat_timeout_ms: float | None = None,
                 sdo_timeout_ms: float = 300.0, bitrate: int | None = None, master_id: int = 127,
                 master_heartbeat_ms: int = 100, master_timeout_ms: float | None = None,
                 on_master_loss: str | None = "quick_stop", encoder: str = "referenced", seat_margin: int = 30,
                 url: str = "") -> None:
        if len(nodes) != model.n_joints:
            raise ConfigError(f"canopen: {len(nodes)} node ids {nodes} for model {model.name} with "
                              f"{model.n_joints} joints; give one node per joint (nodes=1-{model.n_joints})")
        for i, j in enumerate(model.joints):
            if j.encoder is None:
                raise ConfigError(f"canopen: joint {i + 1} ({j.name}) of model {model.name} has no encoder scaling")
        if not (0.0005 <= sync_period <= 1.0) or not (10 <= heartbeat_ms <= 10000):
            raise ConfigError(f"canopen: sync period {sync_period * 1e3:g} ms must be 0.5..1000 and heartbeat "
                              f"{heartbeat_ms} ms 10..10000")
        if heartbeat_timeout_ms is not None and heartbeat_timeout_ms <= heartbeat_ms:
            raise ConfigError(f"canopen: heartbeat_timeout_ms={heartbeat_timeout_ms:g} must exceed heartbeat_ms="
                              f"{heartbeat_ms} (the consumer time covers at least one producer period)")
        master_timeout_ms = master_timeout_ms or 3 * master_heartbeat_ms + 500
        if master_timeout_ms <= master_heartbeat_ms:
            raise ConfigError(f"canopen: master_timeout_ms={master_timeout_ms:g} must exceed master_heartbeat_ms="
                              f"{master_heartbeat_ms} (the drives' consumer time covers at least one period)")
        self.model = model
        self.nodes = list(nodes)
        self.url = url
        self.encoder = encoder
        self.seat_margin = seat_margin
        self._serial = serial
        self._identity: Identity | None = None
        self._interrupt = threading.Event()  # set by stop() from any thread: ends a waited move
        self.home_signs: dict[int, int] = {}  # node -> sign of its home offset convention, learned by a homing
        self._found_limits: dict[int, dict[int, int]] = {}  # node -> its torque limit objects as found
        self._limits: dict[int, dict[int, int]] = {}  # what set_compliant(False) must put back (seating on)
        self.faults = FaultLatch()
        self.faults.on_first.append(self._quick_stop_all)
        self.bus = CanopenBus(self.nodes, self.faults, interface=interface, channel=channel, host=host, port=port,
                              sync_period=sync_period, heartbeat_ms=heartbeat_ms, touch_ms=touch_ms, eds=eds,
                              error_frame_limit=error_frame_limit, heartbeat_timeout_ms=heartbeat_timeout_ms,
                              sdo_timeout_ms=sdo_timeout_ms, bitrate=bitrate,
                              master=MasterLoss(master_id, master_heartbeat_ms, master_timeout_ms, on_master_loss))
        try:
            self.bus.open(contact, self._on_emcy)
            # a model for another arm, a drive in rpm or in other position units must not move this one: all
            # read and checked before the first RPDO
            self.units = read_units(self.bus, model, self.nodes)
            snap = self.bus.round(timeout=max(1.0, 20 * sync_period))
            if encoder != "absolute":
                self._check_referenced()
            # hold position: the RPDOs carry the present position and profile position mode from now on
            for node_id in self.nodes:
                self.bus.preset_target(node_id, snap[node_id][1])
                self.bus.send_rpdo2(node_id, MODE_PP, 0, 0)
            self._wait_mode(MODE_PP)
            self._connected = True
        except BaseException:
            self.close()
            raise

    @classmethod
    def from_url(cls, url: RobotURL, **overrides) -> CanopenRobot:
        o = cls.options.parse(url)
        model = cls.load_url_model(url, o["model"], o["tip_link"], o["base_link"])
        args = dict(sync_period=o["sync_ms"] / 1000.0, heartbeat_ms=o["heartbeat_ms"], touch_ms=o["touch_ms"],
                    contact=o["contact"], eds=o["eds"], serial=o["serial"], error_frame_limit=o["error_frames"],
                    heartbeat_timeout_ms=o["heartbeat_timeout_ms"], sdo_timeout_ms=o["sdo_timeout_ms"],
                    bitrate=o["bitrate"], master_id=o["master_id"], master_heartbeat_ms=o["master_heartbeat_ms"],
                    master_timeout_ms=o["master_timeout_ms"], on_master_loss=o["on_master_loss"],
                    encoder=o["encoder"], seat_margin=o["seat_margin"], url=url.raw)
        args.update(overrides)
        nodes = o["nodes"] or list(range(1, model.n_joints + 1))
        interface = url.scheme.partition("+")[2]
        if not url.scheme.startswith("canopen+") or interface not in INTERFACES:
            raise ConfigError(f"robot URL {url.raw!r}: scheme {url.scheme!r} is not a CANopen scheme (canopen+"
                              f"{'|'.join(INTERFACES)})")
        if interface == "socketcand":
            if not url.host or not url.port:
                raise ConfigError(f"robot URL {url.raw!r}: give host:port of the socketcand server")
            return cls(model, nodes, interface="socketcand", channel=o["channel"] or "can0", host=url.host,
                       port=url.port, **args)
        # the channel as written (the netloc keeps its case: PCAN_USBBUS1), or a device path (slcan:///dev/ttyACM0)
        channel = o["channel"] or url.netloc or (url.path if interface == "slcan" else url.path.strip("/"))
        if not channel:
            raise ConfigError(f"robot URL {url.raw!r}: give the {interface} channel, canopen+{interface}://CHANNEL?...")
        return cls(model, nodes, interface=interface, channel=channel, **args)

    @property
    def contact_node(self) -> int | None:
        return self.bus.contact_node

    # ---- faults -------------------------------------------------------------------------------------------
    def _quick_stop_all(self) -> None:
        """Quick stop every drive by RPDO (no SDO: safe from the bus thread and with dead nodes), then keep
        re-sending it from a helper thread to every drive whose fresh TPDO still says OPERATION ENABLED: a
        bus-off controller loses what it sends until its restart time is over (bounded: 2 heartbeat timeouts)."""
        for node_id in self.bus.drives:
            with contextlib.suppress(Exception):
                self.bus.send_rpdo1(node_id, CW_QUICK_STOP)
        threading.Thread(target=self._quick_stop_until_confirmed, name="canopen-quick-stop", daemon=True).start()

    def _quick_stop_until_confirmed(self) -> None:
        bus = self.bus
        t0 = time.monotonic()
        deadline = t0 + max(1.0, 2 * bus.hb_timeout)
        fault = self.faults.error  # this fault's quick stop only: an enable() that cleared it ends the re-sending
        while time.monotonic() < deadline and not bus.closing and self.faults.error is fault is not None:
            time.sleep(max(4 * bus.sync_period, 0.02))
            if self.faults.error is not fault:
                return  # cleared while sleeping (the drives may be enabled again on purpose)
            latest = bus.latest()
            running = [n for n in bus.drives if n in latest and latest[n][4] > t0 and state_of(latest[n][1]) == ENABLED]
            if not running and all(n in latest and latest[n][4] > t0 for n in bus.drives):
                return
            for node_id in running:
                with contextlib.suppress(Exception):
                    bus.send_rpdo1(node_id, CW_QUICK_STOP)

    def _on_emcy(self, node_id: int, e) -> None:
        if e.code & 0xFF00 == 0:
            return  # error reset
        joint = self.model.joints[self.nodes.index(node_id)].name
        self.faults.latch(DeviceFault(f"canopen node {node_id} (joint {joint}) EMCY 0x{e.code:04X} "
                                      f"{e.get_desc() or 'device error'} (error register 0x{e.register:02X}); "
                                      "robot stopped", device=f"node {node_id}", code=e.code))

    # ---- waiting for the drives ---------------------------------------------------------------------------
    def _wait(self, what: str, cond, timeout: float, interruptible: bool = False) -> Round:
        """The first SYNC round for which ``cond`` holds, within ``timeout`` of observed time (a turn of this loop
        the station was not scheduled in counts a few SYNC periods at most: the drives' answers were waiting)."""
        deadline = Deadline(timeout, own_gap=max(0.05, 4 * self.bus.sync_period))
        while True:
            if interruptible and self._interrupt.is_set():
                raise SafetyStop(f"canopen {self.bus.where}: move interrupted by stop(); the arm holds where it "
                                 "stopped")
            snap = self.bus.round()
            if cond(snap):
                self.bus.mark_changed()
                return snap
            if deadline.expired():
                self.stop()  # whatever did not happen, nothing keeps moving
                bad = [n for n in self.nodes if n in snap and not _holds(cond, snap, n)]
                raise DeviceFault(f"canopen {self.bus.where}: {what} not confirmed within {timeout:.1f} s "
                                  f"(node(s) {bad}; {deadline.note()})", device=f"node {bad[0]}" if bad else None)

    def _wait_mode(self, mode: int) -> Round:
        return self._wait(f"mode of operation {mode}", lambda s: all(v[2] == mode for v in s.values()), 1.0)

    def _check_referenced(self) -> None:
        """Before anything moves: every drive's position means what it meant before power-off. CiA 402 homing
        mode shows it (statusword bit 12 "homing attained"); an incremental encoder, or a single-turn one without
        a battery, powers up counting from where the joint stood (Kinco FD: the multi-turn data are kept by the
        battery), so the joint reads wrong by whole motor turns / gear until it is homed. Refused in one line."""
        nodes = []
        for node_id in self.nodes:
            modes = self.bus.read_opt(node_id, 0x6502, 0, "u32")
            if modes is not None and not modes & SUPPORTS_HOMING:
                raise ConfigError(f"canopen node {node_id}: no homing mode (0x6502 = 0x{modes:08X}), so whether its "
                                  "position is referenced cannot be read; nothing was moved: if its encoder is "
                                  "absolute (or battery-buffered multi-turn), say encoder=absolute in the robot URL")
            nodes.append(node_id)
        for node_id in nodes:
            self.bus.send_rpdo2(node_id, MODE_HM, 0, 0)
        snap = self._wait(f"mode of operation {MODE_HM}", lambda s: all(v[2] == MODE_HM for v in s.values()), 1.0)
        lost = [n for n in nodes if not snap[n][0] & SW_HOMING_ATTAINED or snap[n][0] & SW_HOMING_ERROR]
        if lost:
            n = lost[0]
            joint = self.model.joints[self.nodes.index(n)].name
            raise ConfigError(f"canopen node(s) {lost} (joint {joint}{', ...' if len(lost) > 1 else ''}): position "
                              "not referenced (homing not attained since power-up: an incremental or single-turn "
                              "encoder counts from where the joint stood, whole motor turns off); nothing was moved: "
                              "home the drive (CiA 402 homing mode with the arm's reference, in its commissioning "
                              "tool) or, if the encoder is absolute, say encoder=absolute in the robot URL")

    def _require_enabled(self, snap: Round) -> None:
        off = [n for n in self.nodes if state_of(snap[n][0]) != ENABLED]
        if off:
            raise SafetyStop(f"canopen: drive(s) {off} not enabled "
                             f"({', '.join(sorted({state_of(snap[n][0]) for n in off}))}); "
                             "clear the cause, then resume the session (jog UI: press c)")

    def _to_q(self, counts) -> np.ndarray:
        return np.array([float(j.encoder.to_si(c)) for j, c in zip(self.model.joints, counts, strict=True)])

    # ---- Robot protocol -----------------------------------------------------------------------------------
    def identity(self) -> Identity:
        if self._identity is None:
            devices = []
            for i, node_id in enumerate(self.nodes):
                ident = {k: self.bus.sdo_read(node_id, 0x1018, s) for s, k in
                         ((1, "vendor_id"), (2, "product_code"), (3, "revision"), (4, "serial"))}
                devices.append({"node": node_id, "joint": self.model.joints[i].name,
                                "name": self.bus.sdo_read(node_id, 0x1008),
                                "hardware": self.bus.sdo_read(node_id, 0x1009),
                                "firmware": self.bus.sdo_read(node_id, 0x100A), **ident})
            first = devices[0]
            serial = self._serial or f"{first['vendor_id']:08X}-{first['serial']:08X}"
            self._identity = Identity(vendor=f"{first['name']} (CiA vendor 0x{first['vendor_id']:08X})",
                                      model=self.model.name, serial=serial, firmware=first["firmware"],
                                      devices=tuple(devices), url=self.url,
                                      serial_source="url" if self._serial else "derived")
        return self._identity

    def joint_positions(self) -> JointSnapshot:
        self.faults.raise_if_latched()
        snap = self.bus.round()
        counts = tuple(int(snap[n][1]) for n in self.nodes)
        t = max(v[3] for v in snap.values())
        return JointSnapshot(q=self._to_q(counts), raw=counts, raw_unit="count", t=t)

    def move_joints(self, q: np.ndarray, speed: float | None = None, wait: bool = True) -> None:
        self.faults.raise_if_latched()
        target = self._checked_target(q, "move_joints")
        speed = self._checked_speed(speed, "move_joints")
        vmax = self.model.max_velocity
        limit = vmax * 0.25 if speed is None else np.minimum(speed, vmax)  # default 25 % of each joint's max
        self._check_stiff("move_joints")
        self._interrupt.clear()
        # state and start position from the newest round (<= 1 cycle old): the profile velocities only scale
        # the joints to arrive together, each stays <= its limit whatever the start, so a cycle-old start is safe
        snap = self.bus.recent()
        self._require_enabled(snap)
        q0 = self._to_q([snap[n][1] for n in self.nodes])
        dq = np.abs(target - q0)
        duration = float(np.max(dq / limit))
        if duration <= 0:
            return
        for i, node_id in enumerate(self.nodes):
            enc = self.model.joints[i].encoder
            per_unit = abs(enc.counts_per_unit * enc.gear)
            # synchronised: all joints arrive together; in the drive's own velocity unit (increments/s or rpm)
            v = self.units[node_id].velocity(dq[i] / duration * per_unit)
            self.bus.send_rpdo2(node_id, MODE_PP, v, 0)
            counts = int(round(float(enc.to_counts(target[i]))))
            self.bus.send_rpdo1(node_id, CW_ENABLE | CW_NEW_SETPOINT | CW_IMMEDIATE, counts)
        self._wait("set-point acknowledge", lambda s: all(v[0] & SW_SETPOINT_ACK for v in s.values()), 1.0)
        for node_id in self.nodes:
            self.bus.send_rpdo1(node_id, CW_ENABLE)
        if wait:
            self._wait("target reached", lambda s: all(v[0] & SW_TARGET_REACHED and not v[0] & SW_SETPOINT_ACK
                                                       for v in s.values()), 2.0 * duration + 2.0,
                       interruptible=True)
            self.faults.raise_if_latched()

    def jog(self, mode: str, axis: int, step: float, speed: float | None = None) -> None:
        self.faults.raise_if_latched()
        q0 = self.joint_positions().q
        target, lead = self._jog_plan(q0, mode, axis, step, speed, joint_default=0.1,
                                      tool_default=MANUAL_TOOL_SPEED_CAP / 2)
        self.move_joints(target, speed=lead, wait=True)

    def stop(self) -> None:
        """Halt every drive (controlword bit 8): decelerate and hold, drives stay enabled; a waited move in
        another thread ends with SafetyStop."""
        self._interrupt.set()
        latest = self.bus.latest()
        sent = False
        for node_id in self.bus.drives:
            # only to drives that are enabled: the halt controlword carries "enable operation", which would take
            # a drive in SWITCHED ON or QUICK STOP ACTIVE (a fault's quick stop) back to OPERATION ENABLED
            if node_id in latest and state_of(latest[node_id][1]) != ENABLED:
                continue
            with contextlib.suppress(Exception):
                self.bus.send_rpdo1(node_id, CW_ENABLE | CW_HALT)
                sent = True
        if sent and self.faults.error is None:
            # a halt nobody answered is no stop: every drive must report once after it (a silent drive raises,
            # naming the node, and the fault latches: the teardown says so instead of a quiet PASS)
            self.bus.round()

    def enable(self) -> None:
        """Fault reset where needed, then every drive to OPERATION ENABLED holding its present position.
        Clears a latched fault only once the cause is gone (heartbeats back, bus up)."""
        self._check_open("enable")
        if isinstance(self.faults.error, ConnectionLost) and (self.bus.silent_nodes() or self.faults.fatal):
            raise self.faults.error
        self.faults.clear()
        self._secured = False
        for node in self.bus.drives.values():
            node.emcy.reset()
        if self.bus.restart_preoperational():  # a heartbeat event sent them to PRE-OPERATIONAL: no PDOs there
            time.sleep(2 * self.bus.sync_period)
        if self._limits:  # seating limits still set (a fault ended the seating): stiff again before enabling
            self._restore_limits()
        self._compliant = False
        self.bus.consumers_watching()  # no drive enabled that would not notice the station go silent
        snap = self.bus.round()
        for node_id in self.nodes:
            self.bus.preset_target(node_id, snap[node_id][1])
            self.bus.send_rpdo2(node_id, MODE_PP, 0, 0)
        self._enable_all(snap)
        self.faults.raise_if_latched()

    def _enable_all(self, snap: Round, timeout: float = 1.0) -> None:
        """CiA 402 power state machine of every drive at once: each round, every drive not yet OPERATION
        ENABLED gets the controlword of its next transition (fault reset 2-edge, shutdown, switch on, enable
        operation), and the next SYNC round confirms it; a drive needs up to 4 rounds, all drives together too
        (one drive after another waited up to 3 rounds each). ``timeout`` is observed time."""
        last: dict[int, int] = {}
        deadline = Deadline(timeout, own_gap=max(0.05, 4 * self.bus.sync_period))
        while True:
            pending = {n: state_of(snap[n][0]) for n in self.nodes if state_of(snap[n][0]) != ENABLED}
            if not pending:
                self.bus.mark_changed()
                return
            if deadline.expired():
                n, st = next(iter(pending.items()))
                err = DeviceFault(f"canopen node {n}: cannot enable (stays in {st} after {timeout:g} s; "
                                  f"node(s) {sorted(pending)} not enabled; {deadline.note()})", device=f"node {n}")
                self.faults.latch(err)
                raise err
            for n, st in pending.items():
                cw = next_controlword(st, last.get(n))
                if cw is None:
                    continue
                last[n] = cw
                self.bus.send_rpdo1(n, cw)
            snap = self.bus.round()

    def disable(self) -> None:
        self.stop()
        for node_id in self.bus.drives:
            with contextlib.suppress(Exception):
                self.bus.send_rpdo1(node_id, CW_SHUTDOWN)
        if self._compliant:
            with contextlib.suppress(StationError):
                self._restore_limits()

    def status(self) -> RobotStatus:
        latest = self.bus.latest()
        joints, faults = [], list(self.faults.messages)
        for i, node_id in enumerate(self.nodes):
            name = self.model.joints[i].name
            sw = latest.get(node_id, (0, 0))[1]
            st = state_of(sw)
            fault = None
            if st in FAULTED:
                active = self.bus.drives[node_id].emcy.active
                fault = f"EMCY 0x{active[-1].code:04X}" if active else "FAULT"
                faults.append(f"node {node_id} ({name}): {fault}")
            enabled = st == ENABLED
            joints.append(JointState(name, enabled, enabled and not sw & SW_TARGET_REACHED, fault))
        return RobotStatus(enabled=all(j.enabled for j in joints), moving=any(j.moving for j in joints),
                           faults=tuple(dict.fromkeys(faults)), compliant=self._compliant, joints=tuple(joints))

    # ---- capabilities: ContactSensor, Compliant, CalibrationStore -----------------------------------------
    def touch(self) -> bool | None:
        if self.bus.contact_node is None:
            return None
        self.faults.raise_if_latched()
        return bool(self.bus.digital_inputs() >> CONTACT_BIT & 1)

    def set_compliant(self, on: bool) -> None:
        """On: the arm yields so a socket can seat the tip, without sagging and without pushing hard: every drive
        stays in profile position mode holding where it is, with its torque limits (0x60E0 positive, 0x60E1
        negative; 0x6072 on drives without them) reduced to the torque holding the joint takes (0x6077, read
        while it holds) plus ``seat_margin`` (and at least 10 % of it) in the direction gravity needs, the margin
        alone in the other. Never a bare torque set-point: in profile torque mode nothing holds position, light
        joints accelerate and loaded ones sag. Off: the held target moved to where the arm settled first (else
        the restored torque would pull it back out of the socket), then the limits found before. Off with a fault
        latched (bus-off, heartbeat loss, EMCY): position mode cannot be trusted any more, so every drive is
        disabled instead (power stage off, holding brake engaged) through whatever path still works, and the
        error says what was and was not confirmed."""
        if not on and self.faults.error is not None:
            err = self.faults.error
            report = self._disable_after_fault()
            raise type(err)(f"{err}; compliance off not possible: {report}")
        self.faults.raise_if_latched()
        self._check_open("set_compliant")
        if not on:
            if self._compliant:
                snap = self.bus.round()
                if all(state_of(v[0]) == ENABLED for v in snap.values()):
                    self._hold_here(snap)
                self._restore_limits()
            self._compliant = False
            return
        self._require_enabled(self.bus.recent())
        if self._compliant:
            return
        missing = [n for n in self.nodes if n not in self._found_limits]
        # the drive's own limits, read once per connection (the station's are put back)
        self._found_limits.update(self.bus.per_node(missing, lambda n: {
            i: v for i in (0x6072, 0x60E0, 0x60E1) if (v := self.bus.read_opt(n, i, 0, "u16")) is not None}))
        for node_id in self.nodes:
            if not {0x6072, 0x60E0, 0x60E1} & set(self._found_limits[node_id]):
                raise ConfigError(f"canopen node {node_id}: no torque limit (0x6072, 0x60E0/0x60E1) to seat with: "
                                  "the arm cannot yield to a socket")
        self._limits = {n: self._found_limits[n] for n in self.nodes}
        self._compliant = True  # from the first reduced limit on, off must restore them

        def seat(node_id: int) -> None:
            hold = self.bus.read_obj(node_id, 0x6077, 0, "i16")
            margin = max(self.seat_margin, int(math.ceil(SEAT_RELATIVE * abs(hold))))
            have = self._limits[node_id]
            if 0x60E0 in have and 0x60E1 in have:
                self.bus.write_obj(node_id, 0x60E0, 0, "u16", min(0xFFFF, max(hold, 0) + margin))
                self.bus.write_obj(node_id, 0x60E1, 0, "u16", min(0xFFFF, max(-hold, 0) + margin))
            else:
                self.bus.write_obj(node_id, 0x6072, 0, "u16", min(0xFFFF, abs(hold) + margin))

        self.bus.per_node(self.nodes, seat)
        self.bus.round()  # a drive applies new limits in its control cycle: the next SYNC round has them
        self.bus.mark_changed()

    def _hold_here(self, snap: Round) -> None:
        """New set-point = the present position of every drive (a socket moved the arm while it yielded)."""
        for i, node_id in enumerate(self.nodes):
            enc = self.model.joints[i].encoder
            slow = 0.1 * float(self.model.max_velocity[i]) * abs(enc.counts_per_unit * enc.gear)
            self.bus.send_rpdo2(node_id, MODE_PP, self.units[node_id].velocity(slow), 0)
            self.bus.send_rpdo1(node_id, CW_ENABLE | CW_NEW_SETPOINT | CW_IMMEDIATE, snap[node_id][1])
        self._wait("set-point acknowledge", lambda s: all(v[0] & SW_SETPOINT_ACK for v in s.values()), 1.0)
        for node_id in self.nodes:
            self.bus.send_rpdo1(node_id, CW_ENABLE)

    def _restore_limits(self) -> None:
        """The torque limits each drive had before seating (only those the seating changed)."""
        def restore(node_id: int) -> None:
            found = self._limits[node_id]
            both = 0x60E0 in found and 0x60E1 in found
            for index, value in found.items():
                if (index == 0x6072) != (not both):
                    continue
                self.bus.write_obj(node_id, index, 0, "u16", value)

        self.bus.per_node(list(self._limits), restore)
        self._limits = {}
        self.bus.round()

    def read_calibration(self) -> dict[str, float]:
        """The zero each drive applies to its encoder, ``0x6064 - 0x6063``, in SI:
        ``offset.jN = direction * counts / (counts_per_unit * gear)`` (docs/hardware-canopen.md)."""
        out = {}
        for i, node_id in enumerate(self.nodes):
            enc = self.model.joints[i].encoder
            counts = read_zero(self.bus, node_id).offset
            out[f"offset.j{i + 1}"] = enc.direction * counts / (enc.counts_per_unit * enc.gear)
        return out

    def persist_calibration(self) -> list[int]:
        """Re-send the store command (0x1010:03 "save", application parameters) to every drive and return the
        nodes that confirmed it (SDO download acknowledged). Idempotent: what a resume or verify of an interrupted
        write-back calls, because a zero set by homing but not yet stored is lost at the next power cycle;
        ``DeviceFault`` naming the node that refused it."""
        self._check_open("persist_calibration")
        self._store(self.nodes)
        return list(self.nodes)

    def _store(self, nodes: list[int]) -> None:
        """0x1010:03 with only what must persist changed: the station's runtime application parameters (its
        reaction to a lost station 0x6007) go back to what the drive had while the store runs."""
        if self._compliant:
            raise SafetyStop("canopen: a calibration is not stored while the arm is compliant (its torque limits "
                             "are the seating ones); switch compliance off first")
        with self.bus.as_found(nodes):
            for node_id in nodes:
                self.bus.store_parameters(node_id)

    def write_calibration(self, values: dict[str, float]) -> None:
        """New absolute zero offsets (SI): homing on the current position makes each take effect (the home offset
        0x607C alone does not), proved by the joint's reported position changing by the expected amount at the
        same physical pose; then stored (0x1010:03) and read back. Refused while a fault is latched (EMCY, bus
        error, lost node): a calibration is never started on a drive train in error."""
        self._check_open("write_calibration")
        self.faults.raise_if_latched()
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
                raise ConfigError(f"write_calibration: {name} = {value:g} does not fit the drive's position range")
            plan[self.nodes[idx]] = (name, counts)
        if self._compliant:
            raise SafetyStop("canopen: write_calibration while the arm is compliant (seating torque limits); "
                             "switch compliance off first")
        ZeroSetter(self).apply({n: c for n, (_name, c) in plan.items()})
        self._store(list(plan))
        for node_id, (name, counts) in plan.items():
            back = read_zero(self.bus, node_id).offset
            if abs(back - counts) > 1:
                raise DeviceFault(f"write_calibration: node {node_id} ({name}) reads back a zero of {back} counts, "
                                  f"wrote {counts}", device=f"node {node_id}")

    # ---- the safe state after a fault -----------------------------------------------------------------------
    _connected = False  # __init__ completed: the drives hold in profile position mode under this robot
    _secured = False  # every drive confirmed disabled after the latest fault (close() need not repeat it)
    _secure_tried = False  # a _disable_after_fault ran (close() repeats it only while the link can come back)
    SAFE_STATES = ("SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON", "FAULT", "NOT READY TO SWITCH ON")

    def _disable_after_fault(self, timeout: float | None = None) -> str:
        """Bring every drive to a power-stage-off state (CiA 402: quick stop, then SWITCH ON DISABLED; the
        drive engages its holding brake) after a fault, retrying through the bus's recovery (a bus-off
        controller is back after its restart time): first by RPDO1 controlword, then by SDO 0x6040 for the
        drives whose TPDOs do not confirm. Never raises; returns what was confirmed, and loudly what was not."""
        bus = self.bus
        deadline = time.monotonic() + (timeout if timeout is not None else max(1.0, 2 * bus.hb_timeout))
        pending = set(self.nodes)
        sent_at = time.monotonic()
        stopping: set[int] = set()  # reached QUICK STOP ACTIVE (decelerated): next, disable voltage
        while pending and time.monotonic() < deadline:
            for node_id in sorted(pending):
                with contextlib.suppress(Exception):
                    bus.send_rpdo1(node_id, CW_DISABLE_VOLTAGE if node_id in stopping else CW_QUICK_STOP)
            time.sleep(max(4 * bus.sync_period, 0.02))
            latest = bus.latest()
            for node_id in sorted(pending):
                seen = latest.get(node_id)
                if seen is not None and seen[4] > sent_at:
                    state = state_of(seen[1])
                    if state in self.SAFE_STATES:
                        pending.discard(node_id)
                    elif state == "QUICK STOP ACTIVE":
                        stopping.add(node_id)
            for node_id in sorted(pending):  # no fresh TPDO: ask and command over SDO
                try:
                    state = state_of(int(bus.sdo_read(node_id, 0x6041)))
                    if state in self.SAFE_STATES:
                        pending.discard(node_id)
                    else:
                        if state == "QUICK STOP ACTIVE":
                            stopping.add(node_id)
                        bus.sdo_write(node_id, 0x6040, CW_DISABLE_VOLTAGE if node_id in stopping else CW_QUICK_STOP)
                except Exception:  # noqa: BLE001 - that path is down too: keep trying until the deadline
                    pass
        self._compliant = False
        self._secured = not pending
        self._secure_tried = True
        done = [n for n in self.nodes if n not in pending]
        if not pending:
            return f"every drive disabled instead (power stage off, brakes engaged; confirmed on nodes {done})"
        return (f"drives NOT confirmed disabled on nodes {sorted(pending)} (confirmed: {done or 'none'}): "
                "switch off drive power at the cabinet before approaching the arm")

    # ---- lifecycle ----------------------------------------------------------------------------------------
    def _shutdown(self) -> None:
        """Halt, then every drive to READY TO SWITCH ON (power stage off) unless a fault already quick-stopped
        them; stop SYNC and disconnect."""
        bus = getattr(self, "bus", None)
        if bus is None:
            return
        bus.closing = True
        if bus.drives and self.faults.error is None and self._connected:
            with contextlib.suppress(Exception):  # a drive that does not answer the halt latches a fault: below
                self.stop()
        if bus.drives and self.faults.error is None and not self._connected:
            bus.release_consumers()  # refused at connect: nothing was commanded, nothing to take back
        elif bus.drives and self.faults.error is None:
            with contextlib.suppress(Exception):
                time.sleep(2 * bus.sync_period)
                for node_id in bus.drives:
                    bus.send_rpdo1(node_id, CW_SHUTDOWN)
            if self._compliant:
                with contextlib.suppress(Exception):
                    self._restore_limits()
            bus.release_consumers()  # shut down cleanly: the drives need not watch for the station any more
        elif bus.drives and not self._secured and self._secure_tried and bus.link_closed():
            # the socketcand server closed the connection (it cannot come back on this bus object): a second
            # attempt would only wait out its deadline again (2 x the heartbeat consumer time)
            log.warning("canopen: closing after a fault: drives NOT confirmed disabled (the CAN link %s is closed): "
                        "switch off drive power at the cabinet before approaching the arm", bus.where)
        elif bus.drives and not self._secured:
            report = self._disable_after_fault()
            # the fault itself is the caller's error line; only a drive left unconfirmed is worth a warning
            (log.info if self._secured else log.warning)("canopen: closing after a fault: %s", report)
        bus.close()
