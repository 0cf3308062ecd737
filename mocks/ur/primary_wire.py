"""Primary / secondary client interface (ports 30001 / 30002) as a UR controller sends it, big-endian.

Layout after Universal Robots' "Client Interface" documentation and the parser of Universal_Robots_Client_Library
(``primary_parser.h``, ``version_message.cpp``, ``robot_mode_data.cpp``, ``kinematics_info.cpp``):

- package: ``int32 length`` (whole package, header included), ``uint8 type``; ROBOT_STATE = 16, ROBOT_MESSAGE = 20;
- robot state: sub-packages ``int32 length, uint8 type, fields``: ROBOT_MODE_DATA = 0, KINEMATICS_INFO = 5;
- KinematicsInfo: ``uint32 checksum[6]``, ``double dh_theta[6], dh_a[6], dh_d[6], dh_alpha[6]`` (published DH plus
  the factory deltas), ``calibration_status``: one byte in the documentation, four on real controllers (the client
  library's comment: "According to the docs this should be uint8_t, but then I have 3 bytes left"); sent as four
  here, the reader takes both;
- robot message: ``uint64 timestamp, int8 source, uint8 message type``; VERSION = 3: ``int8 name length, name,
  uint8 major, uint8 minor, int32 bugfix, int32 build, build date`` (the rest of the package)."""

from __future__ import annotations

import struct

ROBOT_STATE, ROBOT_MESSAGE = 16, 20
ROBOT_MODE_DATA, KINEMATICS_INFO = 0, 5
MESSAGE_VERSION = 3
SOURCE_CONTROLLER = -2


def package(kind: int, body: bytes) -> bytes:
    return struct.pack(">iB", 5 + len(body), kind) + body


def sub_package(kind: int, body: bytes) -> bytes:
    return struct.pack(">iB", 5 + len(body), kind) + body


def version_message(timestamp_us: int, major: int, minor: int, bugfix: int, build: int, date: str) -> bytes:
    name = b"URControl"
    body = struct.pack(">QbB", timestamp_us, SOURCE_CONTROLLER, MESSAGE_VERSION)
    body += struct.pack(">b", len(name)) + name + struct.pack(">BBii", major, minor, bugfix, build) + date.encode()
    return package(ROBOT_MESSAGE, body)


def robot_mode_data(timestamp_us: int, *, powered: bool, estop: bool, pstop: bool, running: bool, paused: bool,
                    robot_mode: int) -> bytes:
    body = struct.pack(">Q7?bBddd", timestamp_us, True, True, powered, estop, pstop, running, paused, robot_mode,
                       0, 1.0, 1.0, 1.0)
    return sub_package(ROBOT_MODE_DATA, body)


def kinematics_info(checksum, theta, a, d, alpha, status: int) -> bytes:
    body = struct.pack(">6I", *checksum) + struct.pack(">24d", *theta, *a, *d, *alpha) + struct.pack(">I", status)
    return sub_package(KINEMATICS_INFO, body)


def robot_state(*subs: bytes) -> bytes:
    return package(ROBOT_STATE, b"".join(subs))
