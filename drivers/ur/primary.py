"""Reader of the one thing the station needs from a UR controller's primary client interface (port 30001; the
secondary interface 30002 carries the same robot state): the KinematicsInfo sub-package of the robot state
message, i.e. the controller's own DH table (published values plus its factory calibration deltas), their
checksums and calibration status.

ur_rtde does not speak this interface and no maintained Python parser of it exists on PyPI, so this is a small
one, after Universal Robots' "Client Interface" documentation and Universal_Robots_Client_Library
(``primary_parser.h``, ``kinematics_info.cpp``, ``version_message.cpp``):

- package: ``int32 length`` (whole package, header included), ``uint8 type`` (16 robot state, 20 robot message);
- robot state: sub-packages ``int32 length, uint8 type`` ...; KinematicsInfo is type 5: ``uint32 checksum[6]``,
  ``double dh_theta[6], dh_a[6], dh_d[6], dh_alpha[6]``, ``calibration_status`` (one byte in the documentation,
  four on real controllers: both are taken);
- robot message type 3 (version): ``uint64 timestamp, int8 source, uint8 3, int8 n, name[n], uint8 major,
  uint8 minor, int32 bugfix, int32 build, date``.

Units: m and rad as sent. The wait counts only silence this process could observe (``Silence``)."""

from __future__ import annotations

import contextlib
import math
import socket
import struct
from dataclasses import dataclass

from station.robot.errors import BusError, ConfigError, ConnectionLost
from station.robot.silence import Silence

PRIMARY_PORT = 30001
ROBOT_STATE, ROBOT_MESSAGE, KINEMATICS_INFO, VERSION = 16, 20, 5, 3
MAX_PACKAGE = 1 << 20  # a longer length field is a broken stream, not a package
READ_TIMEOUT_S = 3.0  # the robot state comes at 10 Hz; KinematicsInfo is in the first one of a connection
MAX_DH_LENGTH = 1e4  # m: plain-DH d of nearly parallel joints is ~1e2-1e3 m; beyond this it is no UR table


@dataclass(frozen=True)
class KinematicsInfo:
    """The controller's DH rows (SI), as sent."""

    checksum: tuple[int, ...]
    theta: tuple[float, ...]
    a: tuple[float, ...]
    d: tuple[float, ...]
    alpha: tuple[float, ...]
    calibration_status: int
    version: str = ""  # "URControl 5.11.1.108318" from the version message, when it came first

    @property
    def checksum_text(self) -> str:
        """The six checksums as one identity string (journaled: a changed calibration is a different one)."""
        return "-".join(f"{c:08x}" for c in self.checksum)


def parse_kinematics(body: bytes) -> KinematicsInfo:
    """One KinematicsInfo sub-package body (after its ``int32 length, uint8 type``)."""
    if len(body) not in (24 + 192 + 1, 24 + 192 + 4):
        raise ValueError(f"KinematicsInfo of {len(body)} bytes (expected 217 or 220)")
    checksum = struct.unpack_from(">6I", body, 0)
    vals = struct.unpack_from(">24d", body, 24)
    status = body[216] if len(body) == 217 else struct.unpack_from(">I", body, 216)[0]
    theta, a, d, alpha = (tuple(vals[6 * k:6 * k + 6]) for k in range(4))
    for name, row in (("dh_theta", theta), ("dh_a", a), ("dh_d", d), ("dh_alpha", alpha)):
        if not all(math.isfinite(v) for v in row):
            raise ValueError(f"{name} has a value that is not finite: {list(row)}")
    if any(abs(v) > MAX_DH_LENGTH for v in (*a, *d)):
        raise ValueError(f"DH lengths beyond {MAX_DH_LENGTH:g} m: a {list(a)}, d {list(d)}")
    return KinematicsInfo(checksum, theta, a, d, alpha, int(status))


def parse_version(body: bytes) -> str:
    """The version message body after ``uint64 timestamp, int8 source, uint8 type``."""
    n = struct.unpack_from(">b", body, 0)[0]
    name = body[1:1 + n].decode("latin-1")
    major, minor, bugfix, build = struct.unpack_from(">BBii", body, 1 + n)
    return f"{name} {major}.{minor}.{bugfix}.{build}"


def kinematics_in(package: bytes) -> KinematicsInfo | None:
    """The KinematicsInfo of one robot-state package body (after the package header), or None."""
    pos = 0
    while pos < len(package):
        if len(package) - pos < 5:
            raise ValueError("robot state: truncated sub-package header")
        size, kind = struct.unpack_from(">iB", package, pos)
        if size < 5 or pos + size > len(package):
            raise ValueError(f"robot state: sub-package of type {kind} claims {size} bytes")
        if kind == KINEMATICS_INFO:
            return parse_kinematics(package[pos + 5:pos + size])
        pos += size
    return None


class _Stream:
    def __init__(self, sock: socket.socket, host: str, port: int, timeout: float) -> None:
        self.sock, self.host, self.port, self.timeout = sock, host, port, timeout
        self.buf = bytearray()
        self.silence = Silence()

    def read(self, n: int) -> bytes:
        while len(self.buf) < n:
            try:
                chunk = self.sock.recv(65536)
            except TimeoutError:
                chunk = None
            except OSError as e:
                raise ConnectionLost(f"ur://{self.host}: primary interface (port {self.port}) connection lost "
                                     f"({e})") from None
            if chunk == b"":
                raise ConnectionLost(f"ur://{self.host}: the controller closed the primary interface (port "
                                     f"{self.port})")
            if chunk:
                self.buf += chunk
                self.silence.reset()
            elif self.silence.tick() > self.timeout:
                raise BusError(f"ur://{self.host}: primary interface timeout: no KinematicsInfo on port {self.port} "
                               f"within {self.timeout:g} s ({self.silence.note()}); PolyScope before 3.6 sends none: "
                               "give the controller's calibration.conf with calibration=PATH")
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out


def read_kinematics(host: str, port: int = PRIMARY_PORT, timeout: float = READ_TIMEOUT_S) -> KinematicsInfo:
    """Connect to the primary interface, read until the robot state carries KinematicsInfo, disconnect.
    One-line errors: ``ConnectionLost`` (not reachable / closed), ``BusError`` (nothing within ``timeout`` s of
    observed silence), ``ConfigError`` (a package that is not what the documentation describes)."""
    try:
        sock = socket.create_connection((host, port), timeout=min(timeout, 2.0))
    except OSError as e:
        raise ConnectionLost(f"ur://{host}: primary interface {host}:{port} not reachable ({e}); enable the "
                             "primary client interface (Settings > Security > Services) or give "
                             "calibration=PATH") from None
    sock.settimeout(0.05)  # short waits: the silence is counted by turns of this loop
    stream = _Stream(sock, host, port, timeout)
    version = ""
    try:
        while True:
            size, kind = struct.unpack(">iB", stream.read(5))
            if not 5 <= size <= MAX_PACKAGE:
                raise ConfigError(f"ur://{host}: primary interface (port {port}) sent a package of {size} bytes: "
                                  "not a UR controller's client interface")
            body = stream.read(size - 5)
            try:
                if kind == ROBOT_MESSAGE and len(body) >= 10 and body[9] == VERSION:
                    version = parse_version(body[10:])
                elif kind == ROBOT_STATE:
                    info = kinematics_in(body)
                    if info is not None:
                        return KinematicsInfo(info.checksum, info.theta, info.a, info.d, info.alpha,
                                              info.calibration_status, version)
            except (ValueError, struct.error) as e:
                raise ConfigError(f"ur://{host}: primary interface (port {port}): {e}") from None
    finally:
        with contextlib.suppress(OSError):
            sock.close()
