"""Client of the tracker line protocol (``station-tracker/1``, docs/map.md "Tracker protocol"): one request line,
one answer line, over TCP (``tcp://HOST:PORT``).

Every wait is bounded (connect, each answer, the whole settle-and-measure loop); every failure is one line
(``ConnectionLost`` for a dead or silent instrument, ``DeviceFault`` for a reading it refuses,
``ConfigError`` for a bad URL). Values are SI: m, rotation vector in rad, the instrument's own frame."""

from __future__ import annotations

import contextlib
import math
import socket
import time

from station.instruments.base import InstrumentBase
from station.instruments.protocol import InstrumentIdentity, PoseReading
from station.robot.errors import ConfigError, ConnectionLost, DeviceFault
from station.robot.url import Option, Options, RobotURL, number

PROTOCOL = "station-tracker/1"
DEFAULT_TIMEOUT = 2.0  # s per answer
SETTLE_TIMEOUT = 10.0  # s: how long MEASURE may keep answering "moving" before it is a fault
MAX_LINE = 4096


class TrackerClient(InstrumentBase):
    """A connection to a tracker at ``tcp://HOST:PORT``; ``close()`` is safe to call twice."""

    options = Options(
        Option("timeout_ms", number(1, 60_000, unit="ms"), DEFAULT_TIMEOUT * 1e3, "wait for each answer"),
        Option("settle_ms", number(0, 600_000, unit="ms"), SETTLE_TIMEOUT * 1e3,
               "how long MEASURE may answer 'moving' (the probe settling) before it is a fault"),
    )
    url_example = "tcp://HOST:PORT"

    def __init__(self, host: str, port: int, *, timeout: float = DEFAULT_TIMEOUT,
                 settle_timeout: float = SETTLE_TIMEOUT, url: str | None = None) -> None:
        self.host, self.port, self.timeout, self.settle_timeout = host, port, timeout, settle_timeout
        self.url = url or f"tcp://{host}:{port}"
        self.where = f"tracker tcp://{host}:{port}"
        self._sock: socket.socket | None = None
        self._buf = b""
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as e:
            self._closed = True
            raise ConnectionLost(f"{self.where}: cannot connect ({e.strerror or e})") from None
        self._sock.settimeout(timeout)
        try:
            reply = self._request("ID")
            parts = reply.split()
            if not parts or parts[0] != PROTOCOL:
                raise ConnectionLost(f"{self.where}: not a {PROTOCOL} instrument (ID answered {reply[:60]!r})")
        except BaseException:
            self.close()
            raise
        self.serial = parts[1] if len(parts) > 1 else ""
        self.spec = dict(p.split("=", 1) for p in parts[2:] if "=" in p)

    @classmethod
    def from_url(cls, url: str | RobotURL, **overrides) -> TrackerClient:
        u, opts = cls.parse(url)
        host, port = parse_url(u.raw)
        kw = {"timeout": opts["timeout_ms"] / 1e3, "settle_timeout": opts["settle_ms"] / 1e3, **overrides}
        return cls(host, port, url=u.raw, **kw)

    def identity(self) -> InstrumentIdentity:
        return InstrumentIdentity(self.serial, self.spec.get("model"), "tracker", PROTOCOL, dict(self.spec))

    # ---- the wire ------------------------------------------------------------------------------------
    def _line(self) -> str:
        while b"\n" not in self._buf:
            try:
                chunk = self._sock.recv(4096)
            except TimeoutError:
                raise ConnectionLost(f"{self.where}: no answer within {self.timeout:g} s") from None
            except OSError as e:
                raise ConnectionLost(f"{self.where}: connection lost ({e.strerror or e})") from None
            if not chunk:
                raise ConnectionLost(f"{self.where}: the instrument closed the connection")
            self._buf += chunk
            if len(self._buf) > MAX_LINE:
                raise ConnectionLost(f"{self.where}: answer longer than {MAX_LINE} bytes")
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode("ascii", errors="replace").strip()

    def _request(self, command: str) -> str:
        """Send one request; the answer after ``OK`` (``ERR ...`` raises DeviceFault)."""
        if self._closed:
            raise ConnectionLost(f"{self.where}: connection is closed")
        try:
            self._sock.sendall(command.encode("ascii") + b"\n")
        except OSError as e:
            raise ConnectionLost(f"{self.where}: connection lost ({e.strerror or e})") from None
        reply = self._line()
        if reply.startswith("OK"):
            return reply[2:].strip()
        if reply.startswith("ERR"):
            raise DeviceFault(f"{self.where}: {command}: {reply[3:].strip()[:200]}", device="tracker")
        raise ConnectionLost(f"{self.where}: {command}: unexpected answer {reply[:60]!r}")

    # ---- measuring -----------------------------------------------------------------------------------
    def measure(self) -> PoseReading:
        """One stationary 6-DoF reading; while the instrument answers ``ERR moving`` it asks again, at most
        ``settle_timeout`` seconds."""
        self._check_open("MEASURE")
        end = time.monotonic() + self.settle_timeout
        while True:
            try:
                reply = self._request("MEASURE")
                break
            except DeviceFault as e:
                if ": moving" not in str(e) or time.monotonic() > end:
                    raise
                time.sleep(0.02)
        try:
            v = [float(s) for s in reply.split()]
        except ValueError:
            raise ConnectionLost(f"{self.where}: MEASURE: malformed answer {reply[:80]!r}") from None
        if len(v) != 7 or not all(math.isfinite(x) for x in v):
            raise ConnectionLost(f"{self.where}: MEASURE: expected 'x y z rx ry rz t', got {reply[:80]!r}")
        return PoseReading((v[0], v[1], v[2]), (v[3], v[4], v[5]), v[6])

    def _shutdown(self) -> None:
        if self._sock is None:
            return
        with contextlib.suppress(OSError):
            self._sock.settimeout(0.5)
            self._sock.sendall(b"QUIT\n")
        with contextlib.suppress(OSError):
            self._sock.close()


def parse_url(url: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` -> (host, port); ConfigError in one line otherwise."""
    from urllib.parse import urlsplit

    try:
        u = urlsplit(str(url))
        port = u.port
    except ValueError:
        raise ConfigError(f"tracker URL {url!r}: expected tcp://HOST:PORT") from None
    if u.scheme != "tcp" or not u.hostname or not port:
        raise ConfigError(f"tracker URL {url!r}: expected tcp://HOST:PORT")
    return u.hostname, port


def open_tracker(url: str, **kw) -> TrackerClient:
    """Connect to the tracker at ``url`` (``tcp://HOST:PORT[?timeout_ms=..&settle_ms=..]``) and identify it."""
    return TrackerClient.from_url(url, **kw)
