"""``station.mocks.ur.primary_wire`` and ``rtde_wire``: the bytes the UR controller emulator sends, decoded here
by hand from Universal Robots' documents (Client Interface: ``int32 length, uint8 type`` packages, big-endian;
RTDE guide: ``uint16 size, uint8 type`` headers, recipe types) and by the station driver's own parser."""

from __future__ import annotations

import math
import struct

import numpy as np
from station.drivers.ur.primary import kinematics_in, parse_version
from station.mocks.ur import primary_wire as pw
from station.mocks.ur import rtde_wire as rw

THETA = [0.0, 1e-4, -2e-4, 0.0, 3e-4, 0.0]
A = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0]
D = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996]
ALPHA = [math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]


def test_robot_state_with_kinematics_info_by_the_document_and_by_the_driver():
    msg = pw.robot_state(pw.robot_mode_data(123, powered=True, estop=False, pstop=False, running=True, paused=False,
                                            robot_mode=7),
                         pw.kinematics_info([1, 2, 3, 4, 5, 6], THETA, A, D, ALPHA, 1))
    size, kind = struct.unpack_from(">iB", msg, 0)
    assert size == len(msg) and kind == 16  # ROBOT_STATE
    pos, subs = 5, {}
    while pos < len(msg):
        n, t = struct.unpack_from(">iB", msg, pos)
        subs[t] = msg[pos + 5:pos + n]
        pos += n
    assert pos == len(msg) and set(subs) == {0, 5}
    k = subs[5]
    assert struct.unpack_from(">6I", k, 0) == (1, 2, 3, 4, 5, 6)
    vals = struct.unpack_from(">24d", k, 24)
    assert list(vals[6:12]) == A and list(vals[12:18]) == D
    info = kinematics_in(msg[5:])  # the station's parser agrees
    assert info.a == tuple(A) and info.alpha == tuple(ALPHA) and info.calibration_status == 1
    assert info.checksum_text == "00000001-00000002-00000003-00000004-00000005-00000006"
    mode = subs[0]
    assert struct.unpack_from(">Q", mode, 0)[0] == 123 and struct.unpack_from(">b", mode, 15)[0] == 7


def test_version_message():
    msg = pw.version_message(5, 5, 15, 0, 108318, "01-01-2024")
    size, kind = struct.unpack_from(">iB", msg, 0)
    assert size == len(msg) and kind == 20  # ROBOT_MESSAGE
    ts, source, mtype = struct.unpack_from(">QbB", msg, 5)
    assert (source, mtype) == (-2, 3)
    assert parse_version(msg[5 + 10:]) == "URControl 5.15.0.108318"


def test_rtde_frames_and_recipes():
    f = rw.frame(rw.DATA_PACKAGE, b"\x01abc")
    assert struct.unpack_from(">HB", f) == (len(f), ord("U"))
    types = [rw.OUTPUTS["timestamp"], rw.OUTPUTS["actual_q"], rw.OUTPUTS["robot_mode"]]
    assert types == ["DOUBLE", "VECTOR6D", "INT32"]  # as the RTDE guide lists them
    values = [12.5, list(np.arange(6) * 0.1), 7]
    s = rw.recipe_struct(types)
    packed = s.pack(*rw.flatten(values, types))
    assert len(packed) == 8 + 48 + 4
    assert rw.unflatten(s.unpack(packed), types) == values
    assert rw.split_names(b"timestamp,actual_q,") == ["timestamp", "actual_q"]  # ur_rtde 1.6.5's trailing comma
