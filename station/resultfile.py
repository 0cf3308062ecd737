"""Read a calibration result JSON (``station-calibration/1``, written by ``station solve --out``) strictly:
the fields a calibrated model is built from are checked by schema before any is used (docs/formats.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import ConfigDict, Field

from station.robot.errors import ConfigError
from station.safeio import read_json
from station.strict import Name, NonNeg, Num, Strict, check

FORMAT = "station-calibration/1"


class _Parameter(Strict):
    value: Num | None  # null: the data did not determine it (then it is not identifiable)
    std: NonNeg | None = None
    identifiable: bool
    reason: str | None = None
    nominal: Num | None = None
    kind: Name = "model"
    unit: Literal["m", "rad", "rad/(N m)", "m/N", "1"] = "m"
    prior_std: NonNeg | None = None  # the prior the MAP estimate used (None: none)
    shrinkage: Num | None = None  # how far the prior pulled the estimate (0: the data alone)
    prior_share: Num | None = None  # the prior's share of the estimate's information (0: the data alone)
    fix: str | None = None  # for a parameter not identified: what would identify it
    cause: str | None = None  # structural cause of a non-identifiable parameter


class CalibrationSchema(Strict):
    """What ``station fk --calibration`` relies on; the rest of a result (residuals, covariance, notes) is
    report material and passes through."""

    model_config = ConfigDict(extra="allow", strict=True, allow_inf_nan=False, frozen=True)
    format: Literal["station-calibration/1"]
    units: Literal["SI (m, rad)"]
    model: Name
    parameters: dict[Name, _Parameter] = Field(max_length=100_000)


def load_calibration(path: str | Path, model):
    """``model`` calibrated by the result file ``path``; ``ConfigError`` in one line naming file and field."""
    from station.solver import CalibrationResult

    name = f"calibration {path}"
    doc = read_json(path, "calibration")
    if isinstance(doc, dict) and isinstance(doc.get("model"), str) and doc["model"] != model.name:
        raise ConfigError(f"{name}: model: the calibration is for {doc['model']!r}, not {model.name!r}")
    cal = check(CalibrationSchema, doc, ConfigError, name)
    for n, p in cal.parameters.items():
        if p.identifiable and p.value is None:
            raise ConfigError(f"{name}: parameters.{n}: identifiable but its value is null")
        if p.kind == "model" and p.identifiable and n not in model.param_names:
            raise ConfigError(f"{name}: parameters.{n}: model {model.name!r} has no such parameter")
        if p.kind == "model" and p.identifiable and p.value is not None:
            _check_physical(name, n, p.value, float(model.params[model.index(n)]), p.unit)
    if cal.model != model.name:
        raise ConfigError(f"{name}: model: the calibration is for {cal.model!r}, not {model.name!r}")
    try:
        return CalibrationResult.from_dict(doc).calibrated(model)
    except (ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"{name}: {e}") from None


MAX_ANGLE_CHANGE = 3.141592653589793  # rad: a zero offset or twist correction beyond half a turn is no calibration
MAX_LENGTH_CHANGE = 1.0  # m: a link length, TCP or base correction beyond a metre is a unit slip or another robot


def _check_physical(name: str, n: str, value: float, nominal: float, unit: str) -> None:
    """A calibration value beyond physical bounds (|offset| > pi, a length changed by more than 1 m) is refused
    in one line: applied, it would silently turn the model into another robot."""
    change = value - nominal
    if unit == "rad" and abs(change) > MAX_ANGLE_CHANGE:
        raise ConfigError(f"{name}: parameters.{n}: value {value:.6g} rad is {change:+.6g} rad from nominal: beyond "
                          f"half a turn, no calibration (a unit slip, degrees as radians?)")
    if unit == "m" and abs(change) > MAX_LENGTH_CHANGE:
        raise ConfigError(f"{name}: parameters.{n}: value {value:.6g} m is {change:+.6g} m from nominal: a length "
                          f"changed by more than 1 m is no calibration (a unit slip, millimetres as metres?)")
