"""The units a CiA 402 drive counts in, read before any motion: scaled where the station can, refused in one line
where it cannot.

- Position (0x60A8 SI unit position; factor group 0x608F encoder increments per motor revolution, 0x6091 gear
  motor : shaft revolutions, 0x6092 feed per shaft revolutions): the drive's position units per joint revolution
  must equal the model's encoder (counts_per_rev x gear), in increments. A drive counting in another resolution
  (e.g. 2^16 per motor revolution) or in degrees is refused: the model of this arm says otherwise, and a joint
  would move by the wrong angle.
- Velocity (0x60A9 SI unit velocity): increments per second, or revolutions per minute of the motor with a
  power-of-ten prefix (Synapticon's default 1 rpm = 0x00B44700, 0.001 rpm = 0xFDB44700; Nanotec's preset
  00B44700h). The station's profile velocities are converted; any other unit is refused. A drive without the
  object counts in position units per second (CiA 402).

Units on the wire: SI codes are ``exponent (bits 24-31) | unit (16-23) | time unit (8-15)``."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from station.robot.errors import ConfigError, IdentityMismatch

UNIT_INC = 0x00B50000  # increments (position)
UNIT_INC_PER_S = 0x00B50300  # increments per second
UNIT_RPM = 0x00B44700  # revolutions per minute
UNIT_MASK = 0x00FFFFFF


def exponent(code: int) -> int:
    return struct.unpack("b", bytes([code >> 24 & 0xFF]))[0]


@dataclass(frozen=True)
class DriveUnits:
    """One drive: ``per_velocity_unit`` = position units (= model counts) per second in one unit of 0x6081."""

    node: int
    per_velocity_unit: float
    velocity_name: str

    def velocity(self, counts_per_s: float) -> int:
        """Profile velocity in the drive's unit, at least 1 (0 would not move a drive that takes it literally)."""
        return max(1, int(math.ceil(abs(counts_per_s) / self.per_velocity_unit)))


def read_units(bus, model, nodes: list[int]) -> dict[int, DriveUnits]:
    """Check every drive's position scaling against the model and read its velocity unit (SDO, at connect; the
    drives at once). The first refusal in node order is raised."""
    return bus.per_node(nodes, lambda node_id: _units(bus, model, nodes.index(node_id), node_id))


def _units(bus, model, i: int, node_id: int) -> DriveUnits:
    joint = model.joints[i]
    enc = joint.encoder
    model_per_rev = abs(enc.counts_per_unit * enc.gear) * 2 * math.pi  # counts per joint revolution
    pos_unit = bus.read_opt(node_id, 0x60A8, 0, "u32")
    if pos_unit not in (None, 0) and pos_unit & UNIT_MASK != UNIT_INC:
        raise ConfigError(f"canopen node {node_id} (joint {i + 1} {joint.name}): position unit 0x60A8 = "
                          f"0x{pos_unit:08X} is not encoder increments; nothing was moved: set 0x60A8 to "
                          "increments (0x00B50000) with the drive's tool, the station's model counts in them")
    if joint.kind == "revolute":
        _check_position_scaling(bus, model, i, node_id, model_per_rev)
    inc, mrev = (bus.read_opt(node_id, 0x608F, s, "u32") for s in (1, 2))
    motor_rev = (inc / mrev) if inc and mrev else abs(enc.counts_per_unit) * 2 * math.pi
    code = bus.read_opt(node_id, 0x60A9, 0, "u32")
    if code in (None, 0) or code & UNIT_MASK == UNIT_INC_PER_S:
        e = exponent(code) if code else 0
        return DriveUnits(node_id, 10.0 ** e, "increments/s" if not e else f"1e{e} increments/s")
    if code & UNIT_MASK == UNIT_RPM:
        e = exponent(code)
        name = "rpm" if not e else f"{10.0 ** e:g} rpm"
        return DriveUnits(node_id, motor_rev / 60.0 * 10.0 ** e, name)
    raise ConfigError(f"canopen node {node_id} (joint {i + 1} {joint.name}): velocity unit 0x60A9 = "
                      f"0x{code:08X} is neither increments/s nor rpm; nothing was moved: set 0x60A9 to "
                      "rpm (0x00B44700) or increments/s (0x00B50300) with the drive's tool")


def _check_position_scaling(bus, model, i: int, node_id: int, model_per_rev: float) -> None:
    """A rotary joint's drive scaling (0x608F, 0x6091, 0x6092) against the model's encoder: a scara model on an
    arm6's drives, a model with the wrong gear, or a drive counting 2^16 per motor revolution would move joints
    by the wrong angle. Drives without these optional objects are not checked (the 402 device type at connect
    still is)."""
    joint = model.joints[i]
    inc, mrev = (bus.read_opt(node_id, 0x608F, s, "u32") for s in (1, 2))
    gm, gs = (bus.read_opt(node_id, 0x6091, s, "u32") for s in (1, 2))
    feed, shaft = (bus.read_opt(node_id, 0x6092, s, "u32") for s in (1, 2))
    if feed and shaft:
        drive_per_rev = feed / shaft  # position units per shaft (joint) revolution
        how = f"feed constant {feed}:{shaft}"
    elif inc and mrev:
        drive_per_rev = inc / mrev * ((gm / gs) if gm and gs else 1.0)
        how = f"{inc / mrev:g} counts/motor rev" + (f", gear {gm}:{gs}" if gm and gs else "")
    else:
        return
    if abs(drive_per_rev - model_per_rev) > 1e-6 * model_per_rev:
        raise IdentityMismatch(
            f"canopen node {node_id} (joint {i + 1} {joint.name}) is scaled {how} = {drive_per_rev:.10g} "
            f"counts/rev but model {model.name} says {abs(joint.encoder.counts_per_unit) * 2 * math.pi:.10g} x gear "
            f"{joint.encoder.gear:g} = {model_per_rev:.10g}; nothing was moved: use the model of this arm (its "
            "encoder counts_per_rev and gear as the drive counts)")
