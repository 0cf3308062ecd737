"""A socketcand-protocol hub on a TCP port: python-can's real ``socketcand`` interface connects to it.

vcan is not available on the station's build machines, so a cross-process CAN bus is a TCP server that
speaks the socketcand ASCII protocol (rawmode only) and bridges every client to one python-can bus
(normally the ``virtual`` channel the emulated drives sit on) and to each other.

Protocol as python-can's client (can/interfaces/socketcand) expects it:
``< hi >`` on connect; ``< open NAME >`` -> ``< ok >``; ``< rawmode >`` -> ``< ok >``; then
``< send ID LEN B0 B1 .. >`` from the client and ``< frame ID SECS.USECS DATA >`` to it. The client reads each
handshake reply with a single ``recv`` and compares it exactly, so the hub sends nothing after the rawmode
``< ok >`` until the client has sent a frame or ``rawmode_delay`` passed (bus frames meanwhile are queued, not
lost).

CAN error frames: socketcand's raw mode opens its CAN_RAW socket without CAN_RAW_ERR_FILTER unless the daemon
was started with ``-e ERROR_MASK`` (linux-can/socketcand ``src/state_raw.c``; the option since 2025-05, commit
d9880ef "Enable error frame reception in raw mode"), so by default a client never sees one: bus-off shows only
as silence (heartbeats). The hub does the same: ``error_mask`` 0 (default) forwards no error frame; otherwise
``< error CLASS SECS.USECS >`` for the error classes in the mask, as ``socketcand -e`` does."""

from __future__ import annotations

import collections
import contextlib
import logging
import socket
import threading
import time

import can

log = logging.getLogger("station.mocks.canopen.hub")

DEFAULT_PORT = 29536
CAN_ERR_BUSOFF = 0x40


def frame_text(msg: can.Message) -> str:
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & 0x1FFFFFFF:03X} {msg.timestamp or time.time():.6f} >"
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    data = bytes(msg.data[:msg.dlc]).hex().upper()
    return f"< frame {ident} {msg.timestamp or time.time():.6f} {data} >"


def parse_send(body: str) -> can.Message:
    """``send ID LEN B0 B1 ..`` (hex fields) -> Message; ValueError if malformed."""
    parts = body.split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {body!r}")
    ident, length = parts[1], int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:3 + length])
    if len(data) != length or length > 8:
        raise ValueError(f"send: length {length} does not match {len(parts) - 3} data bytes")
    return can.Message(arbitration_id=int(ident, 16), is_extended_id=len(ident) > 3, data=data)


class _Client:
    def __init__(self, sock: socket.socket, addr) -> None:
        self.sock = sock
        self.addr = addr
        self.lock = threading.Lock()  # one writer at a time on the socket
        self.flow = threading.RLock()  # live/backlog: keeps queued frames in order
        self.opened = False
        self.raw = False  # rawmode answered
        self.live = False  # frames may flow to the client
        self.raw_at = 0.0
        self.backlog: collections.deque[str] = collections.deque(maxlen=10000)
        self.closed = False

    def send(self, text: str) -> bool:
        with self.lock:
            if self.closed:
                return False
            try:
                self.sock.sendall(text.encode("ascii"))
                return True
            except OSError:
                self.closed = True
                return False

    def offer(self, text: str, delay: float) -> None:
        """A bus frame for this client: sent if live, queued while its rawmode ``< ok >`` settles."""
        if not self.raw or self.closed:
            return
        with self.flow:
            if not self.live:
                if time.monotonic() - self.raw_at < delay:
                    self.backlog.append(text)
                    return
                self.go_live()
            self.send(text)

    def go_live(self) -> None:
        with self.flow:
            if self.live:
                return
            self.live = True
            while self.backlog:
                self.send(self.backlog.popleft())

    def close(self) -> None:
        with self.lock:
            self.closed = True
            with contextlib.suppress(OSError):
                self.sock.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                self.sock.close()


class SocketcandHub:
    """Serve the python-can bus ``interface``/``channel`` as socketcand bus ``name`` on ``host:port``."""

    def __init__(self, channel: str, host: str = "127.0.0.1", port: int = DEFAULT_PORT, name: str = "can0",
                 interface: str = "virtual", rawmode_delay: float = 0.05, error_mask: int = 0) -> None:
        self.channel, self.interface = channel, interface
        self.error_mask = error_mask & 0x1FFFFFFF  # socketcand -e: error classes forwarded (0: none, its default)
        self.errors_dropped = 0
        self.host, self.port, self.name = host, port, name
        self.rawmode_delay = rawmode_delay
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._server: socket.socket | None = None
        self._bus: can.BusABC | None = None
        self.frames_to_clients = 0
        self.frames_from_clients = 0

    # ---- lifecycle ----------------------------------------------------------------------------
    def start(self) -> SocketcandHub:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            server.bind((self.host, self.port))
        except OSError as e:
            server.close()
            raise OSError(f"socketcand hub: cannot listen on {self.host}:{self.port}: {e.strerror}") from None
        server.listen(8)
        server.settimeout(0.2)
        self.port = server.getsockname()[1]
        self._server = server
        self._bus = can.Bus(interface=self.interface, channel=self.channel)
        self._stop.clear()
        for target, name in ((self._accept_loop, "accept"), (self._bus_loop, "bus")):
            t = threading.Thread(target=target, name=f"socketcand-hub-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._server is not None:
            with contextlib.suppress(OSError):
                self._server.close()
        self.drop_clients()
        for t in self._threads:
            t.join(timeout=5)
        self._threads = []
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def __enter__(self) -> SocketcandHub:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def drop_clients(self) -> None:
        """Close every client connection (a pulled cable / crashed daemon, for fault tests)."""
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            c.close()

    def inject_error(self, error_class: int = CAN_ERR_BUSOFF) -> None:
        """The hub's CAN controller reports an error (SocketCAN error class bits, e.g. 0x40 bus-off): forwarded
        to the clients only if ``error_mask`` has that class (socketcand -e), else dropped as socketcand does."""
        self._offer_frame(can.Message(arbitration_id=error_class, is_error_frame=True, timestamp=time.time()))

    def _offer_frame(self, msg: can.Message) -> None:
        if msg.is_error_frame and not msg.arbitration_id & self.error_mask:
            self.errors_dropped += 1
            return
        self._to_clients(frame_text(msg), None)

    # ---- threads ------------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, addr = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, addr)
            with self._lock:
                self._clients.append(client)
            t = threading.Thread(target=self._client_loop, args=(client,), name=f"socketcand-client-{addr[1]}",
                                 daemon=True)
            t.start()

    def _bus_loop(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(0.1)
            except (can.CanError, AttributeError):
                return
            if msg is not None:
                self._offer_frame(msg)

    def _to_clients(self, text: str, source: _Client | None) -> None:
        with self._lock:
            clients = [c for c in self._clients if c is not source]
        for c in clients:
            c.offer(text, self.rawmode_delay)
            self.frames_to_clients += 1

    def _client_loop(self, c: _Client) -> None:
        log.info("socketcand hub: client %s connected", c.addr)
        c.send("< hi >")
        buf = ""
        c.sock.settimeout(0.05)
        try:
            while not self._stop.is_set() and not c.closed:
                if c.raw and not c.live and time.monotonic() - c.raw_at >= self.rawmode_delay:
                    c.go_live()
                try:
                    chunk = c.sock.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not chunk:
                    break
                buf += chunk.decode("ascii", errors="replace")
                while True:
                    start, end = buf.find("<"), buf.find(">")
                    if start < 0 or end < 0:
                        if start < 0:
                            buf = ""
                        break
                    if end < start:
                        buf = buf[start:]
                        continue
                    self._command(c, buf[start + 1:end].strip())
                    buf = buf[end + 1:]
        finally:
            with self._lock:
                if c in self._clients:
                    self._clients.remove(c)
            c.close()
            log.info("socketcand hub: client %s left", c.addr)

    def _command(self, c: _Client, body: str) -> None:
        word = body.split(" ", 1)[0]
        if word == "open":
            name = body.split()[1] if len(body.split()) > 1 else ""
            if name != self.name:
                c.send(f"< error could not open bus '{name}' (this hub serves '{self.name}') >")
                return
            c.opened = True
            c.send("< ok >")
        elif word == "rawmode" and c.opened:
            c.raw_at = time.monotonic()
            c.send("< ok >")
            c.raw = True
        elif word == "send" and c.raw:
            try:
                msg = parse_send(body)
            except ValueError as e:
                c.send(f"< error {e} >")
                return
            c.go_live()  # it has read its < ok >
            self.frames_from_clients += 1
            msg.timestamp = time.time()
            self._bus.send(msg)
            self._to_clients(frame_text(msg), c)
        elif word == "echo":
            c.send("< echo >")
        else:
            c.send(f"< error unsupported command '{word}' >")
