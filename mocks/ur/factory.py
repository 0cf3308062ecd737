"""The emulated controller's factory calibration, derived from the world's hidden truth.

A UR controller keeps its arm's kinematic calibration (``calibration.conf``: deltas to the published DH table)
and uses it for everything it computes (``actual_TCP_pose``, ``get_inverse_kin``, ``moveL``). It reports the
resulting DH rows - published values plus deltas, as plain DH - in the KinematicsInfo sub-package of the
primary/secondary client interface (Universal_Robots_Client_Library ``kinematics_info.h``: "a combination
between the perfect model parameters and the correction deltas"). Plain DH of a real arm has the compensating
``d`` of hundreds of metres and ``theta`` near +-pi/2 on its nearly parallel joints (UR ROS driver
``ur_calibration/doc/algorithm.rst``); ``station.kinematics.dhtable`` computes exactly those rows.

What the factory knew is the world's choice (``buses.ur.calibration``):

- ``links`` (default): the hidden link geometry (every ``dh.*``/``mdh.*``/``poe.*`` error); the hidden joint zero
  offsets happened since (a joint replaced, a zero lost): they are what ``zero_offsets`` finds;
- ``arm``: link geometry and joint zero offsets: the controller knows the arm exactly;
- ``none``: an uncalibrated controller (the published table, all deltas zero).

Never known: the mounting (``base.*``), the tool (``tcp.*``), compliance and backlash."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from station.kinematics import Model
from station.kinematics.dhtable import DHTable, dh_table

CALIBRATION_CHOICES = ("links", "arm", "none")


@dataclass(frozen=True)
class Factory:
    """What the controller believes about its arm: ``model`` (the flange, no tool), the DH rows it reports,
    their checksums and calibration status."""

    model: Model
    table: DHTable
    published: DHTable
    checksum: tuple[int, ...]
    status: int
    known: dict[str, float]


def _flange(model: Model) -> Model:
    return model.with_params({f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")})


def known_errors(world, which: str) -> dict[str, float]:
    """The hidden errors the factory calibration includes (see the module docstring)."""
    if which not in CALIBRATION_CHOICES:
        raise ValueError(f"buses.ur.calibration: {which!r} is not one of {', '.join(CALIBRATION_CHOICES)}")
    if which == "none":
        return {}
    out = {}
    for name, err in world.errors().items():
        head = name.split(".", 1)[0]
        if head in ("dh", "mdh", "poe") or (which == "arm" and head == "offset"):
            out[name] = err
    return out


def checksum(row) -> int:
    """The emulator's per-joint checksum: CRC-32 of the row's four doubles (big-endian theta, a, d, alpha).
    A real controller's algorithm is not published; the station only records and compares the values."""
    return zlib.crc32(struct.pack(">4d", *(float(v) for v in row))) & 0xFFFFFFFF


def factory(world, which: str = "links") -> Factory:
    nominal = _flange(world.nominal)
    known = known_errors(world, which)
    model = nominal.with_params({n: nominal.param(n) + e for n, e in known.items()})
    published = dh_table(nominal)
    table = dh_table(model, hint=published)
    rows = np.column_stack([table.theta, table.a, table.d, table.alpha])
    return Factory(model, table, published, tuple(checksum(r) for r in rows), 0 if which == "none" else 1, known)
