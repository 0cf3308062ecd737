"""Manufacturing tolerances of a model's parameters: the prior standard deviations of a calibration.

A model file may state them (``tolerances:``, see docs/formats.md); the solver has defaults per group
(``station.solver.priors``) and the command line overrides both (``--prior offsets=0.5deg``). An entry
is ``(selector, std, quantity)``: a group, parameter name or glob, a standard deviation in SI, and
``"length"``, ``"angle"`` or None (None: every parameter the selector names, whatever its quantity;
only from a bare number in a model file, which is read in the file's own units per quantity)."""

from __future__ import annotations

import math
import re

from station.samplesfile import ANGLE_UNITS, LENGTH_UNITS

Tolerance = tuple[str, float, str | None]  # (selector, std in SI, "length" | "angle" | None)

_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-zµ]+)\s*$")


def parse_quantity(text: str) -> tuple[float, str]:
    """``"20um"`` -> ``(2e-05, "length")``, ``"0.5deg"`` -> ``(0.00873, "angle")``: a number with a length
    or angle unit, in SI. Raises ValueError with a one-line message. (The one place where the solver's
    command-line values are read; units from ``station.samplesfile``.)"""
    m = _QUANTITY.match(str(text))
    if not m:
        raise ValueError(f"{text!r}: expected a number with a unit, e.g. 20um, 0.3mm, 0.5deg")
    value, unit = float(m.group(1)), m.group(2).replace("µ", "u")
    if unit in LENGTH_UNITS:
        out = (value * LENGTH_UNITS[unit], "length")
    elif unit in ANGLE_UNITS:
        out = (value * ANGLE_UNITS[unit], "angle")
    else:
        units = ", ".join([*LENGTH_UNITS, *ANGLE_UNITS])
        raise ValueError(f"{text!r}: unknown unit {unit!r} ({units})")
    if not math.isfinite(out[0]):
        raise ValueError(f"{text!r}: not a finite number")
    return out


def parse_tolerances(doc, where: str, length_si: float, angle_si: float) -> tuple[Tolerance, ...]:
    """``tolerances:`` of a model file: ``{selector: value | [value, ...]}``; a value is a number with a unit
    (``0.3mm``, ``0.05deg``) or a bare number in the file's units (``length_si`` / ``angle_si`` per metre /
    radian of the file's unit), which applies to lengths and angles alike. Standard deviations must be > 0."""
    if doc is None:
        return ()
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: tolerances: expected a mapping like {{offsets: 0.5deg, dh: 0.3mm}}")
    out: list[Tolerance] = []
    for sel, vals in doc.items():
        for v in vals if isinstance(vals, list) else [vals]:
            w = f"{where}: tolerances.{sel}"
            if isinstance(v, bool):
                raise ValueError(f"{w}: expected a number with a unit, got {v!r}")
            if isinstance(v, (int, float)):
                if not math.isfinite(v) or v <= 0:
                    raise ValueError(f"{w}: a tolerance must be a positive number, got {v!r}")
                out += [(str(sel), float(v) * length_si, "length"), (str(sel), float(v) * angle_si, "angle")]
                continue
            try:
                std, quantity = parse_quantity(v)
            except ValueError as e:
                raise ValueError(f"{w}: {e}") from None
            if std <= 0:
                raise ValueError(f"{w}: a tolerance must be positive, got {v!r}")
            out.append((str(sel), std, quantity))
    return tuple(out)


def tolerances_to_doc(tols: tuple[Tolerance, ...], length: str, angle: str) -> dict:
    """The ``tolerances:`` mapping of a model file, values with explicit units."""
    doc: dict[str, list[str]] = {}
    for sel, std, quantity in tols:
        unit, k = (angle, ANGLE_UNITS[angle]) if quantity == "angle" else (length, LENGTH_UNITS[length])
        doc.setdefault(sel, []).append(f"{round(std / k, 12):g}{unit}")
    return {s: v[0] if len(v) == 1 else v for s, v in doc.items()}
