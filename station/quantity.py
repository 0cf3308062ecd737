"""Option values with their unit: ``--cone 50deg``, ``--max-std 1mm``, as ``--noise 20um`` always took them. A bare
number keeps its documented unit (degrees for a cone, metres for ``--max-std``), so scripts written before the
suffixes still run. One reading for the command line and for the options procedures declare
(``station.engine.declare``): it imports nothing heavier than ``station.units`` until a value needs it."""

from __future__ import annotations

import math
import re

from station.robot.errors import ConfigError

_TRIPLE = re.compile(r"^\s*([^,]+),([^,]+),([^,]+?)\s*([a-z]*)\s*$")


def parse_option(text, option: str, quantity: str, bare: str, example: str) -> float:
    """``text`` (``50deg``, ``0.87rad``, ``1mm``, or a bare number in unit ``bare``) as a value in ``bare``'s unit
    (``deg`` or ``m``); ``ConfigError`` in one line naming the option otherwise."""
    from station.units import to_si

    if isinstance(text, (int, float)):
        value = float(text)
    else:
        s = str(text).strip()
        try:
            value = float(s)
        except ValueError:
            from station.kinematics.tolerances import parse_quantity

            try:
                si, q = parse_quantity(s)
            except ValueError:
                raise ConfigError(f"{option} {text!r}: expected {'an' if quantity == 'angle' else 'a'} {quantity} "
                                  f"with its unit, e.g. {example} (a bare number is {bare})") from None
            if q != quantity:
                raise ConfigError(f"{option} {text!r}: expected {'an' if quantity == 'angle' else 'a'} {quantity}, "
                                  f"e.g. {example} (a bare number is {bare})") from None
            value = si / to_si(1.0, bare, quantity)
    if not math.isfinite(value):
        raise ConfigError(f"{option} {text!r}: not a finite number")
    return value


def parse_xyz(text: str, option: str):
    """``x,y,z`` in metres, or with one unit suffix for all three: ``100,200,50mm``; a numpy array (m)."""
    import numpy as np

    from station.units import LENGTH_UNITS

    m = _TRIPLE.match(text)
    if not m:
        raise ConfigError(f"{option} {text!r}: expected x,y,z (metres, or with a unit suffix like 100,200,50mm)")
    unit = m.group(4) or "m"
    if unit not in LENGTH_UNITS:
        raise ConfigError(f"{option} {text!r}: unknown length unit {unit!r} (m, mm, cm, um)")
    try:
        v = np.array([float(m.group(k)) for k in (1, 2, 3)]) * LENGTH_UNITS[unit]
    except ValueError:
        raise ConfigError(f"{option} {text!r}: not a number") from None
    if not np.isfinite(v).all():
        raise ConfigError(f"{option} {text!r}: not a finite number")
    return v


MASS_UNITS = {"kg": 1.0, "g": 1e-3}
_PAYLOAD = re.compile(r"^\s*([-+0-9.eE]+)\s*(kg|g)\s*(?:@(.+))?$")


def parse_payload(text: str) -> tuple[float, object]:
    """``0.1kg`` / ``250g`` / ``0.5kg@0,0,30mm`` -> (kg, centre of mass in the tool frame, m)."""
    m = _PAYLOAD.match(text)
    if not m:
        raise ConfigError(f"--payload {text!r}: expected a mass with its unit (0.1kg, 250g), optionally "
                          f"@x,y,z for its centre in the tool frame (0.5kg@0,0,30mm)")
    try:
        mass = float(m.group(1)) * MASS_UNITS[m.group(2)]
    except ValueError:
        raise ConfigError(f"--payload {text!r}: {m.group(1)!r} is not a number") from None
    if not (mass >= 0 and mass < float("inf")):
        raise ConfigError(f"--payload {text!r}: a mass is a finite number >= 0")
    com = (0.0, 0.0, 0.0)
    if m.group(3):
        com = tuple(parse_xyz(m.group(3), "--payload"))
    return mass, com
