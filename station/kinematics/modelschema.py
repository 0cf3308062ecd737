"""The schema of a model file (``station-model/1``, docs/formats.md): shape, types and ranges, checked before
``station.kinematics.modelfile`` reads units and geometry. Kept apart so that reading a built-in model does not
import pydantic (start-up time, measured by bench/startup.py)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, create_model, model_validator

from station.kinematics.modelformat import FORMAT
from station.strict import Name, NonNeg, Num, Pair, Pos, Strict, Text, Vec3, check
from station.yamlfile import YamlDoc


# ---- the schema of a serial model file: the shape, types and ranges (units and geometry: modelfile.py) ----
class _Units(Strict):
    length: Literal["m", "mm"]
    angle: Literal["rad", "deg"]
    mass: Literal["kg"] = "kg"


# a pose (base, tool, home) and a dh/mdh table row: every key a number, 0 when left out
_Frame = create_model("_Frame", __base__=Strict, **{k: (Num, 0.0) for k in ("x", "y", "z", "rx", "ry", "rz")})
_Link = create_model("_Link", __base__=Strict, **{k: (Num, 0.0) for k in ("a", "alpha", "d", "theta", "beta")})


class _Encoder(Strict):
    counts_per_rev: Pos | None = None
    counts_per_m: Pos | None = None
    gear: Pos = 1.0  # the sign is the direction's
    direction: Literal[1, -1] = 1
    zero: Num = 0.0

    @model_validator(mode="after")
    def _one_scale(self):
        if (self.counts_per_rev is None) == (self.counts_per_m is None):
            raise ValueError("needs exactly one of counts_per_rev (revolute) or counts_per_m (prismatic)")
        return self


class _Screw(Strict):
    axis: Vec3
    point: Vec3 = [0.0, 0.0, 0.0]


class _Joint(Strict):
    name: Name | None = None
    type: Literal["revolute", "prismatic"] = "revolute"
    limits: Pair
    max_velocity: Pos = 1.0
    max_acceleration: Pos | None = None
    encoder: _Encoder | None = None
    offset: Num = 0.0
    compliance: NonNeg = 0.0
    mass: NonNeg | None = None
    com: Vec3 | None = None
    dh: _Link | None = None
    mdh: _Link | None = None
    screw: _Screw | None = None


class _Payload(Strict):
    mass: NonNeg
    com: Vec3 = [0.0, 0.0, 0.0]


class _Collision(Strict):
    link_radii: list[NonNeg] | None = None
    tool_radius: NonNeg | None = None
    tool_free: NonNeg | None = None


class SerialModelSchema(Strict):
    """``station-model/1``, kind serial (docs/formats.md)."""

    format: Literal["station-model/1"] = FORMAT
    kind: Literal["serial"] = "serial"
    name: Name | None = None
    description: Text = ""
    convention: Literal["dh", "mdh", "poe"]
    units: _Units
    joints: list[_Joint] = Field(min_length=1, max_length=64)
    base: _Frame | None = None
    tool: _Frame | None = None
    home: _Frame | None = None
    payload: _Payload | None = None
    gravity: Vec3 | None = None
    collision: _Collision | None = None


class _ParallelHead(Strict):
    model_config = {**Strict.model_config, "extra": "allow"}
    units: _Units


def check_schema(doc: YamlDoc, error: type[Exception]) -> None:
    """``doc`` (a parsed mapping) against the serial schema, or the head of a parallel one (the rest is
    station/kinematics/parallelfile.py's); ``error`` in one line naming file, line and field."""
    if doc.data.get("kind", "serial") == "serial":
        check(SerialModelSchema, doc, error)
    else:
        check(_ParallelHead, doc, error)
