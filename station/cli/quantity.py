"""Option values with their unit: ``--cone 50deg``, ``--max-std 1mm``, as ``--noise 20um`` always took them. A bare
number keeps its documented unit (degrees for a cone, metres for ``--max-std``), so scripts written before the
suffixes still run."""

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
