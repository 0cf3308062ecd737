"""Units at the edges, SI inside: the one table of unit names and the one rule for a parameter's quantity.

Files and command lines may say ``mm``/``deg``; everything inside the station is m, rad, s. Every reader
(samples CSV, limits, cell, ``--reference``) and every writer of human numbers (CLI tables, reports, the jog
UI) converts through this module, so a unit name means the same everywhere. Pure Python: cheap to import."""

from __future__ import annotations

import math

# unit name -> SI value of one unit
LENGTH_UNITS: dict[str, float] = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "um": 1e-6}
ANGLE_UNITS: dict[str, float] = {"rad": 1.0, "deg": math.pi / 180.0, "mrad": 1e-3}
NUMBER_UNITS: dict[str, float] = {"count": 1.0, "1": 1.0}
QUANTITY_UNITS: dict[str, dict[str, float]] = {"length": LENGTH_UNITS, "angle": ANGLE_UNITS,
                                               "number": NUMBER_UNITS}
SI_UNIT = {"length": "m", "angle": "rad", "number": "1"}
# how people read each quantity: lengths in mm, angles in degrees
HUMAN_UNIT = {"length": "mm", "angle": "deg", "number": "count"}

# last part of a parameter name that is an angle whatever the convention (rotations of a frame, DH angles)
ANGLE_PARAMS = frozenset({"rx", "ry", "rz", "alpha", "beta", "theta"})


class UnitError(ValueError):
    """An unknown unit name, or a unit of the wrong quantity."""


def quantity_of(unit: str) -> str:
    """``length``, ``angle`` or ``number`` for a unit name; UnitError for an unknown one."""
    for quantity, table in QUANTITY_UNITS.items():
        if unit in table:
            return quantity
    raise UnitError(f"unknown unit {unit!r} (lengths {', '.join(LENGTH_UNITS)}; angles {', '.join(ANGLE_UNITS)})")


def factor(unit: str, quantity: str | None = None) -> float:
    """SI value of one ``unit``; with ``quantity`` the unit must measure it (an angle unit for a length is an
    error, not a silent factor)."""
    q = quantity_of(unit)
    if quantity is not None and q != quantity:
        want = ", ".join(QUANTITY_UNITS[quantity])
        raise UnitError(f"unit {unit!r} measures {q}, expected {quantity} ({want})")
    return QUANTITY_UNITS[q][unit]


def to_si(value: float, unit: str, quantity: str | None = None) -> float:
    return value * factor(unit, quantity)


def from_si(value: float, unit: str, quantity: str | None = None) -> float:
    return value / factor(unit, quantity)


def human(quantity: str) -> tuple[str, float]:
    """``(unit, k)`` to show an SI value of ``quantity`` as people read it: ``value_si * k`` in ``unit``."""
    unit = HUMAN_UNIT.get(quantity, "1")
    return unit, 1.0 / QUANTITY_UNITS.get(quantity, NUMBER_UNITS).get(unit, 1.0)


def human_of(si_unit: str | None) -> tuple[str, float]:
    """``(unit, k)`` for a value given with its SI unit (``rad`` -> deg, ``m`` -> mm, else as is)."""
    return human(unit_quantity(si_unit)) if si_unit in ("rad", "m") else (si_unit or "", 1.0)


def joint_quantity(revolute: bool) -> str:
    return "angle" if revolute else "length"


def joint_unit(revolute: bool) -> str:
    """SI unit of a joint value: rad for a revolute joint, m for a prismatic one."""
    return "rad" if revolute else "m"


def param_quantity(name: str, model=None) -> str:
    """The one rule for a model parameter's quantity (names: docs/formats.md, "Parameter names").

    ``offset.jN`` is the joint's own kind (a prismatic joint's zero offset is a length; without ``model`` a
    revolute joint is assumed); a name ending in ``rx ry rz alpha beta theta`` is an angle; everything else
    (``a d x y z``, ``point.LABEL.*``) is a length."""
    if name.startswith("offset.j"):
        if model is not None:
            try:
                return joint_quantity(bool(model.joints[int(name[len("offset.j"):]) - 1].revolute))
            except (ValueError, IndexError):
                pass
        return "angle"
    return "angle" if name.rsplit(".", 1)[-1] in ANGLE_PARAMS else "length"


def param_unit(name: str, model=None) -> str:
    """SI unit (``rad`` or ``m``) of a model parameter: :func:`param_quantity` as a unit."""
    return SI_UNIT[param_quantity(name, model)]


def unit_quantity(si_unit: str | None) -> str:
    """Quantity of an SI unit as results carry it (``rad`` -> angle, ``m`` -> length)."""
    return {"rad": "angle", "m": "length"}.get(si_unit or "", "number")
