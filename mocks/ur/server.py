"""The controller's TCP ports on one address: RTDE (30004), dashboard server (29999), script port (30003),
primary and secondary client interfaces (30001, 30002: version message, 10 Hz robot state with KinematicsInfo).

Port 30004 is fixed in ur_rtde, so each emulator gets its own loopback address (127.0.0.2, 127.0.0.3, ...).
Every connection runs in its own thread; RTDE output packages are pushed from the controller's tick."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
import struct
import threading
import time

import numpy as np
from station.mocks.emulator import EmulatorBase
from station.mocks.ur import primary_wire as P
from station.mocks.ur import rtde_wire as W
from station.mocks.ur import state as S
from station.mocks.ur.controller import PERIOD, URController, notice

log = logging.getLogger("station.mocks.ur")

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT, PRIMARY_PORT, SECONDARY_PORT = 30004, 29999, 30003, 30001, 30002
PRIMARY_PERIOD = 0.1  # s: the primary/secondary interfaces send the robot state at 10 Hz
# dashboard "safetystatus"/"safetymode" words for the RTDE safety_mode values (RTDE guide)
SAFETY_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
CONTROLLER_VERSION = (5, 11, 1, 108318)  # PolyScope 5.11 -> ur_rtde picks 500 Hz
TRACE = os.environ.get("STATION_UR_TRACE")  # debugging: append every RTDE input package to this file


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed")
        buf += chunk
    return bytes(buf)


class _Conn:
    def __init__(self, server: URServer, sock: socket.socket) -> None:
        self.server, self.sock, self.ctl = server, sock, server.controller
        self.closed = False

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self.sock.close()
        self.server.forget(self)

    def serve(self) -> None:
        try:
            self.run()
        except (ConnectionError, OSError, struct.error):
            pass
        finally:
            self.close()

    def run(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError


class RTDEConn(_Conn):
    """One RTDE client: recipes, start/pause, input packages; output packages from the tick."""

    def __init__(self, server: URServer, sock: socket.socket) -> None:
        super().__init__(server, sock)
        self.send_lock = threading.Lock()
        self.version = 1
        self.out_names: list[str] = []
        self.out_types: list[str] = []
        self.out_struct: struct.Struct | None = None
        self.divider = 1
        self.inputs: dict[int, tuple[list[str], list[str], struct.Struct]] = {}
        self.started = False

    def send(self, kind: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.sock.sendall(W.frame(kind, payload))

    def run(self) -> None:
        while not self.closed:
            size, kind = W.HEADER.unpack(_recv_exact(self.sock, W.HEADER.size))
            payload = _recv_exact(self.sock, size - W.HEADER.size) if size > W.HEADER.size else b""
            self.handle(kind, payload)

    def handle(self, kind: int, payload: bytes) -> None:
        if kind == W.REQUEST_PROTOCOL_VERSION:
            (ver,) = struct.unpack(">H", payload[:2])
            ok = ver in (1, 2)
            if ok:
                self.version = ver
            self.send(kind, struct.pack(">B", int(ok)))
        elif kind == W.GET_URCONTROL_VERSION:
            self.send(kind, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == W.SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif kind == W.SETUP_INPUTS:
            self._setup_inputs(payload)
        elif kind == W.START:
            self.started = self.out_struct is not None or bool(self.inputs)
            self.send(kind, struct.pack(">B", int(self.started)))
        elif kind == W.PAUSE:
            self.started = False
            self.send(kind, struct.pack(">B", 1))
        elif kind == W.DATA_PACKAGE:
            self._input_package(payload)
        else:
            log.info("RTDE: ignoring message type %r", chr(kind))

    def _setup_outputs(self, payload: bytes) -> None:
        if self.version >= 2:
            (freq,) = struct.unpack(">d", payload[:8])
            payload = payload[8:]
        else:
            freq = 125.0
        names = W.split_names(payload)
        types = [W.OUTPUTS.get(n, "NOT_FOUND") for n in names]
        ok = names and "NOT_FOUND" not in types and 0 < freq <= 1.0 / PERIOD
        if ok:
            self.out_names, self.out_types = names, types
            self.out_struct = W.recipe_struct(types)
            self.divider = max(1, round(1.0 / (PERIOD * freq)))
        reply = ",".join(types).encode()
        recipe_id = 1 if ok else 0
        self.send(W.SETUP_OUTPUTS, (struct.pack(">B", recipe_id) if self.version >= 2 else b"") + reply)

    def _setup_inputs(self, payload: bytes) -> None:
        names = W.split_names(payload)
        types = []
        for n in names:
            t = W.INPUTS.get(n, "NOT_FOUND")
            if t != "NOT_FOUND" and not self.server.claim_input(n, self):
                t = "IN_USE"
            types.append(t)
        ok = names and all(t in W.TYPE_FORMATS for t in types)
        recipe_id = 0
        if ok:
            recipe_id = len(self.inputs) + 1
            self.inputs[recipe_id] = (names, types, W.recipe_struct(types))
        self.send(W.SETUP_INPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode())

    def _input_package(self, payload: bytes) -> None:
        recipe_id = payload[0]
        recipe = self.inputs.get(recipe_id)
        if recipe is None:
            return
        names, types, st = recipe
        values = W.unflatten(st.unpack(payload[1:1 + st.size]), types)
        if TRACE:
            with open(TRACE, "a") as f:
                f.write(f"{self.ctl.tick_count} recipe {recipe_id} {dict(zip(names, values, strict=True))}\n")
        self.ctl.write_inputs(names, values)

    def on_tick(self, ctl: URController) -> None:
        if not self.started or self.out_struct is None or ctl.tick_count % self.divider:
            return
        with ctl.lock:
            values = [ctl.value(n) for n in self.out_names]
        values = [_zero(t) if v is None else v for v, t in zip(values, self.out_types, strict=True)]
        body = self.out_struct.pack(*W.flatten(values, self.out_types))
        try:
            self.send(W.DATA_PACKAGE, (struct.pack(">B", 1) if self.version >= 2 else b"") + body)
        except OSError:
            self.close()


def _zero(t: str):
    fmt = W.TYPE_FORMATS[t]
    if fmt[0].isdigit():
        return [0] * int(fmt[0])
    return False if t == "BOOL" else 0


class DashboardConn(_Conn):
    """Line protocol on 29999. Commands starting with ``emulator`` exist only here (fault injection and
    truth read-back for tests); a real controller answers them with "could not understand"."""

    def run(self) -> None:
        self.sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
        f = self.sock.makefile("rb")
        try:
            for raw in f:
                line = raw.decode("utf-8", "replace").strip()
                if not line:
                    continue
                reply, after = self.answer(line)
                self.sock.sendall((reply + "\n").encode())
                if after is not None:
                    after()
                if line.lower() == "quit":
                    break
        finally:
            f.close()

    _STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}

    def answer(self, line: str):
        """The reply line to one dashboard command, and what to do once it is sent (or None)."""
        cmd = line.lower()
        notice(self.ctl.world, dashboard={"command": cmd})
        fixed = self._FIXED.get(cmd)
        if fixed is not None:
            return fixed(self, self.ctl), None
        for prefix, handler in self._PREFIXED:
            if cmd.startswith(prefix):
                return handler(self, line, cmd)
        return f"could not understand: '{line}'", None

    def _popup(self, line: str, cmd: str):
        self.ctl.messages.append(line[6:])
        return "showing popup", None

    def _addtolog(self, line: str, cmd: str):
        self.ctl.messages.append(line[9:])
        return "Added log message", None

    def _emulator_cmd(self, line: str, cmd: str):
        return self.emulator(cmd.split()[1:])

    def _safety(self, ctl, label: str) -> str:
        return f"{label}: {SAFETY_NAMES.get(ctl.safety_mode, 'FAULT')}"

    def _stop(self, ctl) -> str:
        ctl.stop_program()
        return "Stopped"

    def _power_on(self, ctl) -> str:
        ctl.power_on()
        return "Powering on"

    def _power_off(self, ctl) -> str:
        ctl.power_off()
        return "Powering off"

    def _brake_release(self, ctl) -> str:
        ctl.brake_release()
        return "Brake releasing"

    # the controller's commands with no argument: (self, controller) -> reply
    _FIXED = {
        "polyscopeversion": lambda self, ctl: ctl.polyscope,
        "get serial number": lambda self, ctl: ctl.serial,
        "get robot model": lambda self, ctl: ctl.robot_model,
        "is in remote control": lambda self, ctl: str(ctl.remote_control).lower(),
        "robotmode": lambda self, ctl: f"Robotmode: {ctl.mode_name}",
        "safetymode": lambda self, ctl: self._safety(ctl, "Safetymode"),
        "safetystatus": lambda self, ctl: self._safety(ctl, "Safetystatus"),
        "unlock protective stop": lambda self, ctl: ctl.unlock_protective_stop(),
        "close safety popup": lambda self, ctl: "closing safety popup",
        "close popup": lambda self, ctl: "closing popup",
        "stop": _stop,
        "pause": lambda self, ctl: "Pausing program",
        "programstate": lambda self, ctl: (f"{DashboardConn._STATES.get(ctl.runtime_state, 'STOPPED')} "
                                           f"{ctl.program or '<unnamed>'}"),
        "running": lambda self, ctl: f"Program running: {str(ctl.runtime_state == 2).lower()}",
        "power on": _power_on,
        "power off": _power_off,
        "brake release": _brake_release,
        "quit": lambda self, ctl: "Disconnected",
    }
    # commands with an argument: (prefix, handler(self, line, lowercased line) -> (reply, after))
    _PREFIXED = (("popup ", _popup), ("addtolog", _addtolog), ("emulator", _emulator_cmd))

    def emulator(self, args: list[str]):
        """``emulator protective_stop [AFTER]``, ``emulator stall SECONDS [AFTER]``, ``emulator drop SECONDS
        [AFTER]``, ``emulator estop on|off``, ``emulator power_cycle [BOOT_S]``, ``emulator hold_scripts S``,
        ``emulator encoder``, ``emulator tip``, ``emulator registers``, ``emulator stats``, ``emulator log``.
        AFTER (s of controller time) delays the fault, so a client can be mid-command when it bites."""
        if not args:
            return ("emulator: commands: protective_stop [after], stall S [after], drop S [after], "
                    "estop on|off, power_cycle [boot_s], hold_scripts S, encoder, tip, log"), None
        what, rest = args[0], args[1:]
        try:
            nums = [float(x) for x in rest if x not in ("on", "off")]
        except ValueError:
            return f"emulator: bad number in {' '.join(rest)!r}", None
        handler = self._EMULATOR.get(what)
        if handler is None:
            return f"emulator: unknown command {what!r}", None
        return handler(self, self.ctl, nums, rest)

    def _later(self, after: float, fn) -> None:
        """``fn`` after ``after`` s of controller time: counted on the controller's clock, as the motion it should
        interrupt (a wall-clock timer bit before a sim world had moved when the emulator was starved of CPU)."""
        ctl = self.ctl
        if after <= 0:
            fn()
            return
        due = ctl.controller_time() + after

        def wait() -> None:
            while ctl.controller_time() < due and ctl._running:
                time.sleep(0.002)
            fn()

        threading.Thread(target=wait, name="ur-emulator-after", daemon=True).start()

    def _e_protective_stop(self, ctl, nums, rest):
        self._later(nums[0] if nums else 0.0, lambda: ctl.protective_stop("injected on the dashboard"))
        return "emulator: protective stop", None

    def _e_stall(self, ctl, nums, rest):
        seconds = nums[0] if nums else ctl.stall_s
        self._later(nums[1] if len(nums) > 1 else 0.0, lambda: ctl.stall(seconds))
        return "emulator: stalling data stream", None

    def _e_drop(self, ctl, nums, rest):
        seconds = nums[0] if nums else ctl.drop_s
        return "emulator: dropping connections", lambda: self._later(nums[1] if len(nums) > 1 else 0.0,
                                                                     lambda: ctl.drop(seconds))

    def _e_hold_scripts(self, ctl, nums, rest):
        with ctl.lock:
            ctl.hold_scripts_until = ctl.controller_time() + (nums[0] if nums else 10.0)
        return "emulator: holding scripts", None

    def _e_power_cycle(self, ctl, nums, rest):
        boot = nums[0] if nums else self.server.boot_s
        return "emulator: power cycle", lambda: threading.Thread(
            target=self.server.power_cycle, args=(boot,), name="ur-power-cycle", daemon=True).start()

    def _e_estop(self, ctl, nums, rest):
        ctl.emergency_stop(bool(rest) and rest[0] == "on")
        return f"emulator: emergency stop {'on' if ctl.estop else 'off'}", None

    def _e_registers(self, ctl, nums, rest):
        o = ctl.reg_offset
        return (f"emulator: in_int {ctl.in_int[o:o + 3]} out_int {ctl.out_int[o:o + 3]} "
                f"watchdog {ctl.watchdog_hz:g} Hz, "
                f"last write {ctl.controller_time() - ctl.in_int0_written:.3f} s ago (controller time), "
                f"(tick, command) {list(ctl.cmd_log)[-12:]}"), None

    _EMULATOR = {
        "protective_stop": _e_protective_stop,
        "stall": _e_stall,
        "drop": _e_drop,
        "hold_scripts": _e_hold_scripts,
        "power_cycle": _e_power_cycle,
        "estop": _e_estop,
        "encoder": lambda self, ctl, nums, rest: (
            "emulator: " + " ".join(f"{v:.12g}" for v in np.asarray(ctl.world.encoder_q())), None),
        "tip": lambda self, ctl, nums, rest: (
            "emulator: " + " ".join(f"{v:.12g}" for v in np.asarray(ctl.world.tip_true())), None),
        "registers": _e_registers,
        "stats": lambda self, ctl, nums, rest: (
            f"emulator: ticks {ctl.tick_count} late {ctl.late_ticks} max_late_ms {ctl.max_late * 1e3:.1f}", None),
        "log": lambda self, ctl, nums, rest: ("emulator: " + " | ".join(ctl.messages[-20:]), None),
    }


_PROGRAM = re.compile(r"^(?:def|sec)\s+(\w+)\s*\(\s*\)\s*:", re.M)
_END = re.compile(r"^end\s*$", re.M)


class ScriptConn(_Conn):
    """Port 30003: URScript programs. A top-level ``def name():`` ... ``end`` replaces the running program.
    (The real port also streams a 500 Hz realtime state; ur_rtde does not read it, so neither is it sent.)"""

    def run(self) -> None:
        self.read_programs()

    def read_programs(self) -> None:
        buf = ""
        while not self.closed:
            chunk = self.sock.recv(65536)
            if not chunk:
                return
            buf += chunk.decode("utf-8", "replace")
            while True:
                m = _PROGRAM.search(buf)
                if not m:
                    break
                e = _END.search(buf, m.end())
                if not e:
                    break
                text = buf[m.start():e.end()]
                buf = buf[e.end():]
                if self.server.dump_script:
                    with open(self.server.dump_script, "w") as f:
                        f.write(text)
                self.ctl.load_program(m.group(1), text)


def _version_numbers(polyscope: str) -> tuple[int, int, int, int]:
    m = re.search(r"(\d+)\.(\d+)\.(\d+)\.(\d+)", polyscope)
    return tuple(int(x) for x in m.groups()) if m else (5, 11, 1, 0)


class PrimaryConn(ScriptConn):
    """Ports 30001 (primary) and 30002 (secondary): on connect the version message, then the robot state at
    10 Hz: robot mode data in every message, KinematicsInfo in the first one of the connection (the reader
    must take it then). URScript sent here runs like on 30003."""

    def __init__(self, server: URServer, sock: socket.socket) -> None:
        super().__init__(server, sock)
        self.send_lock = threading.Lock()
        self.sent_kinematics = False
        major, minor, bugfix, build = _version_numbers(self.ctl.polyscope)
        date = self.ctl.polyscope.split("(", 1)[1].rstrip(")") if "(" in self.ctl.polyscope else ""
        with contextlib.suppress(OSError):  # a client gone at once: run() ends on the closed socket
            self._send(P.version_message(self._stamp(), major, minor, bugfix, build, date))

    def _stamp(self) -> int:
        return int(self.ctl.controller_time() * 1e6)

    def _send(self, data: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(data)

    def run(self) -> None:
        self.read_programs()

    def on_tick(self, ctl: URController) -> None:
        if ctl.tick_count % round(PRIMARY_PERIOD / PERIOD):
            return
        with ctl.lock:
            subs = [P.robot_mode_data(self._stamp(), powered=ctl.powered, estop=ctl.estop,
                                      pstop=ctl.safety_mode == S.SAFETY_PROTECTIVE_STOP,
                                      running=ctl.runtime_state == S.PLAYING,
                                      paused=ctl.runtime_state == S.PAUSED, robot_mode=ctl.mode)]
            if not self.sent_kinematics:
                f = ctl.factory
                subs.append(P.kinematics_info(f.checksum, f.table.theta, f.table.a, f.table.d, f.table.alpha,
                                              f.status))
        try:
            self._send(P.robot_state(*subs))
            self.sent_kinematics = True
        except OSError:
            self.close()


class URServer(EmulatorBase):
    """Listens on ``host`` for the controller's ports and owns the controller thread (an ``EmulatorBase``:
    ``start()`` returns it, ``stop()``/``close()`` idempotent, ``url``, ``world``, ``power_cycle()``)."""

    def __init__(self, controller: URController, host: str = "127.0.0.1", *, rtde_port: int = RTDE_PORT,
                 dashboard_port: int = DASHBOARD_PORT, script_port: int = SCRIPT_PORT,
                 primary_port: int = PRIMARY_PORT, secondary_port: int = SECONDARY_PORT,
                 dump_script: str | None = None, url: str = "", boot_s: float = 1.0) -> None:
        self.controller = controller
        self.host = host
        self.ports = {rtde_port: RTDEConn, dashboard_port: DashboardConn, script_port: ScriptConn,
                      primary_port: PrimaryConn, secondary_port: PrimaryConn}
        self.dump_script = dump_script
        self._url = url
        self.boot_s = boot_s  # s a power cycle keeps the ports closed (the controller rebooting)
        self.conns: set[_Conn] = set()
        self.claims: dict[str, _Conn] = {}
        self.lock = threading.Lock()
        self.listeners: list[socket.socket] = []
        self.threads: list[threading.Thread] = []
        self.running = False
        controller.publishers = []
        controller.on_drop = self.drop

    @property
    def world(self):
        """The World the controller drives."""
        return self.controller.world

    @property
    def url(self) -> str:
        """The robot URL the station opens for this controller."""
        return self._url or f"ur://{self.host}"

    def _startup(self) -> None:
        self.running = True
        self._listen()
        self.controller.start()

    def power_cycle(self, boot_s: float | None = None) -> None:
        """Switch the controller off and on: every connection drops, the ports refuse connections while it
        boots (``boot_s``), and it comes back as after a power-up (``URController.power_cycle``: POWER_OFF,
        calibration and installation kept)."""
        self._close_listeners()
        self.close_connections()
        self.controller.power_cycle()
        time.sleep(self.boot_s if boot_s is None else boot_s)
        if self.running:
            self._listen()

    def _listen(self) -> None:
        for port, kind in self.ports.items():
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((self.host, port))
            s.listen(8)
            self.listeners.append(s)
            t = threading.Thread(target=self._accept, args=(s, kind), name=f"ur-accept-{port}", daemon=True)
            t.start()
            self.threads.append(t)

    def _accept(self, listener: socket.socket, kind) -> None:
        while self.running:
            try:
                sock, _ = listener.accept()
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(None)
            conn = kind(self, sock)
            with self.lock:
                self.conns.add(conn)
                if isinstance(conn, RTDEConn | PrimaryConn):
                    self.controller.publishers.append(conn)
            threading.Thread(target=conn.serve, name=f"ur-{kind.__name__}", daemon=True).start()

    def claim_input(self, name: str, conn: _Conn) -> bool:
        with self.lock:
            owner = self.claims.get(name)
            if owner is not None and owner is not conn and not owner.closed:
                return False
            self.claims[name] = conn
            return True

    def forget(self, conn: _Conn) -> None:
        with self.lock:
            self.conns.discard(conn)
            if conn in self.controller.publishers:
                self.controller.publishers.remove(conn)
            for name in [n for n, c in self.claims.items() if c is conn]:
                del self.claims[name]

    def _close_listeners(self) -> None:
        for s in self.listeners:
            # shutdown first: a bare close() does not wake the thread blocked in accept(), and the kernel
            # would keep accepting connections on the half-closed listener
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                s.close()
        self.listeners.clear()

    def close_connections(self) -> None:
        with self.lock:
            conns = list(self.conns)
        for c in conns:
            c.close()

    def drop(self, seconds: float) -> None:
        """Connection loss: every socket closes and the ports refuse connections for ``seconds``."""
        self._close_listeners()
        self.close_connections()
        time.sleep(seconds)
        if self.running:
            self._listen()

    def _shutdown(self) -> None:
        """Close every port and stop the controller (also after a start that failed half way)."""
        self.running = False
        self._close_listeners()
        self.close_connections()
        self.controller.stop()
        self.listeners.clear()
