"""Measurement limits from a versioned limits file keyed by robot model (OpenHTF-style measurements).

File format (``station-limits/1``, YAML)::

    format: station-limits/1
    version: "2026.11-1"          # goes into every verdict, so a record says which limits judged it
    models:
      ur5e:                       # robot model name, or "*" for any model without its own entry
        zero_offsets:             # procedure name
          fit_rms:     {high: 0.10, marginal: 0.08, unit: mm}
          offset_abs:  {high: 2.0, unit: deg}
          seated:      {low: 12, unit: count}

Each limit states its unit (``m mm um`` for lengths, ``rad deg mrad`` for angles, ``count`` or ``1`` for pure
numbers); ``low``/``high`` are inclusive bounds, ``marginal`` the start of the band inside a bound where a
pass is flagged marginal. Procedures measure in SI; values are converted to the limit's unit for judging, and a
unit of the wrong quantity (an angle limit for a length) is refused."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import Field

from station import units
from station.robot.errors import ConfigError
from station.strict import Name, Num, Strict, check

FORMAT = "station-limits/1"
NO_LIMITS = "NO LIMITS"  # the verdict of a session with no limits for its model and procedure: never a PASS
# the units a limit may be stated in (station.units), by quantity
UNITS = ("m", "mm", "um", "rad", "deg", "mrad", "count", "1")


def default_limits() -> Path:
    """The shipped ``limits.yaml`` (package data of ``station.procedures``)."""
    from station.engine.procedure import shipped_folder

    return shipped_folder() / "limits.yaml"


class LimitsError(ConfigError):
    """A limits file is unreadable or wrong; the message names the file and the entry."""


# a calibration limit beyond these (SI) is a unit slip (m written where mm was meant), not a tolerance
PLAUSIBLE = {"length": 0.01, "angle": math.radians(10)}


class _Limit(Strict):
    low: Num | None = None
    high: Num | None = None
    marginal: Num | None = None
    unit: Literal["m", "mm", "um", "rad", "deg", "mrad", "count", "1"]


class LimitsSchema(Strict):
    """``station-limits/1`` (docs/formats.md)."""

    format: Literal["station-limits/1"]
    version: Name | int
    models: dict[Name, dict[Name, dict[Name, _Limit]]] = Field(min_length=1)


@dataclass(frozen=True)
class Limit:
    name: str
    unit: str
    low: float | None = None
    high: float | None = None
    marginal: float | None = None  # inside a bound: values beyond it (towards the bound) pass as marginal

    @property
    def quantity(self) -> str:
        return units.quantity_of(self.unit)

    def from_si(self, value: float) -> float:
        return units.from_si(value, self.unit)

    def judge(self, value_si: float | None, quantity: str) -> dict:
        """The measurement dict of the session record: name, value (in ``unit``), unit, low, high, marginal,
        passed."""
        if quantity != self.quantity:
            raise LimitsError(f"limit {self.name!r} is in {self.unit} ({self.quantity}) but the procedure measures "
                              f"a {quantity}; fix the unit in the limits file")
        out = {"name": self.name, "unit": self.unit, "low": self.low, "high": self.high,
               "marginal_at": self.marginal}
        if value_si is None or not math.isfinite(value_si):
            return {**out, "value": None, "passed": False, "marginal": False, "note": "not measured"}
        v = self.from_si(float(value_si))
        passed = (self.low is None or v >= self.low) and (self.high is None or v <= self.high)
        marginal = False
        if passed and self.marginal is not None:
            if self.high is not None and (self.low is None or self.marginal > (self.low + self.high) / 2):
                marginal = v > self.marginal
            else:
                marginal = v < self.marginal
        return {**out, "value": v, "passed": bool(passed), "marginal": bool(marginal)}


@dataclass(frozen=True)
class Limits:
    path: str
    version: str
    sha256: str
    models: dict[str, dict[str, dict[str, Limit]]]

    def for_procedure(self, model: str, procedure: str) -> dict[str, Limit]:
        table = self.models.get(model) or self.models.get("*")
        if table is None:
            raise LimitsError(f"limits file {self.path} (version {self.version}) has no entry for robot model "
                              f"{model!r} and no '*' default; known: {', '.join(sorted(self.models))}")
        if procedure not in table:
            other = self.models.get("*", {})
            if procedure in other:
                return other[procedure]
            raise LimitsError(f"limits file {self.path} (version {self.version}): model {model!r} has no limits "
                              f"for procedure {procedure!r}; it has: {', '.join(sorted(table)) or 'none'}")
        return table[procedure]


def _num(where: str, key: str, v) -> float | None:
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise LimitsError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


def _limit(where: str, name: str, d) -> Limit:
    if not isinstance(d, dict):
        raise LimitsError(f"{where}: expected a mapping like {{high: 0.1, unit: mm}}, got {d!r}")
    extra = set(d) - {"low", "high", "marginal", "unit"}
    if extra:
        raise LimitsError(f"{where}: unknown key(s) {', '.join(sorted(extra))} (use low, high, marginal, unit)")
    unit = str(d.get("unit", ""))
    if unit not in UNITS:
        raise LimitsError(f"{where}: unit {unit or '(missing)'!r} is not one of {', '.join(UNITS)}")
    low, high, marginal = (_num(where, k, d.get(k)) for k in ("low", "high", "marginal"))
    if low is None and high is None:
        raise LimitsError(f"{where}: needs low and/or high")
    if low is not None and high is not None and low > high:
        raise LimitsError(f"{where}: low {low:g} is above high {high:g}")
    if marginal is not None and ((low is not None and marginal < low) or (high is not None and marginal > high)):
        raise LimitsError(f"{where}: marginal {marginal:g} lies outside [low, high]")
    q = units.quantity_of(unit)
    for key, v in (("low", low), ("high", high), ("marginal", marginal)):
        if v is not None and q in PLAUSIBLE and abs(units.to_si(v, unit)) > PLAUSIBLE[q]:
            big = "10 mm" if q == "length" else "10 deg"
            raise LimitsError(f"{where}: {key} {v:g} {unit} is beyond {big}, not a plausible calibration limit "
                              f"(a unit slip: m for mm, rad for mrad?)")
    return Limit(name, unit, low, high, marginal)


def load_limits(path: str | Path | None = None) -> Limits:
    """Read and check a limits file (default: the shipped ``procedures/limits.yaml``)."""
    import hashlib

    from station.yamlfile import parse_yaml_doc, read_capped

    path = Path(path) if path else default_limits()
    text = read_capped(path, LimitsError, f"limits file {path}")
    ydoc = parse_yaml_doc(text, LimitsError, f"limits file {path}")
    doc = ydoc.data
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise LimitsError(f"limits file {path}: expected 'format: {FORMAT}' at the top")
    version = doc.get("version")
    if version is None or str(version).strip() == "":
        raise LimitsError(f"limits file {path}: missing 'version' (limits must be versioned)")
    models = doc.get("models")
    if not isinstance(models, dict) or not models:
        raise LimitsError(f"limits file {path}: 'models' must map robot model names to procedures")
    out: dict[str, dict[str, dict[str, Limit]]] = {}
    for model, procs in models.items():
        if not isinstance(procs, dict):
            raise LimitsError(f"limits file {path}: models.{model} must map procedure names to limits")
        out[str(model)] = {}
        for proc, table in procs.items():
            if not isinstance(table, dict) or not table:
                raise LimitsError(f"limits file {path}: models.{model}.{proc} must map measurement names to limits")
            out[str(model)][str(proc)] = {
                str(n): _limit(f"limits file {path}: models.{model}.{proc}.{n}", str(n), d) for n, d in table.items()}
    check(LimitsSchema, ydoc, LimitsError)  # what the checks above do not name: unknown keys, types, lines
    return Limits(str(path), str(version), hashlib.sha256(text).hexdigest(), out)


def check_limits(procedure: str, measurements, limits: Limits) -> None:
    """Every section of ``limits``  for ``procedure`` against what it
    declares: a judged measurement without a limit, a limit for a measurement it does not take, a limit in a unit
    of another quantity: one line naming the file, the section and the name (``LimitsError``, exit 2).
    ``measurements``: ``station.engine.declare.Measurement`` (name, unit, quantity, doc, judged)."""
    declared = {m.name: m for m in measurements}
    for model, table in sorted(limits.models.items()):
        section = table.get(procedure)
        if section is None:
            continue
        where = f"limits file {limits.path} (version {limits.version}): models.{model}.{procedure}"
        for name, lim in section.items():
            m = declared.get(name)
            if m is None:
                raise LimitsError(f"{where}.{name}: procedure {procedure} measures no {name!r} (it measures: "
                                  f"{', '.join(declared)})")
            if lim.quantity != m.quantity:
                raise LimitsError(f"{where}.{name}: the limit is in {lim.unit} ({lim.quantity}) but {name} is "
                                  f"a {m.quantity} ({m.unit})")
        missing = [m for m in measurements if m.judged and m.name not in section]
        if missing:
            m = missing[0]
            raise LimitsError(f"{where}: no limit for {m.name} ({m.unit}: {m.doc}), which procedure {procedure} "
                              f"declares judged; add e.g. {m.name}: {{high: ..., unit: {m.unit}}}")

