"""The schema of a world file (``station-world/1``, docs/world.md): shape, types and ranges, checked by
``station.strict`` (errors name file, line and field) before ``worldfile`` reads units and the model's own
names (joints, parameters) and applies the defaults in the file's units. ``buses.<bus>`` stays a free-form
mapping: each emulator checks its own settings.

A field typed ``X = None`` without ``| None`` may be left out but not written ``null`` (pydantic does not
validate a default): the hand-written reader refused ``null`` there too."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, create_model
from station.mocks.world.faults import KINDS as FAULT_KINDS
from station.mocks.world.faults import TRIGGERS

from station.strict import Name, NonNeg, Num, Pos, Strict, Vec3

FRAME_KEYS = ("x", "y", "z", "rx", "ry", "rz")

class _Units(Strict):
    length: Literal["m", "mm"]
    angle: Literal["rad", "deg"]
    time: Literal["s"] = "s"
    mass: Literal["kg"] = "kg"


class _Robot(Strict):
    model: Name = "ur5e"
    tool: dict[Literal[FRAME_KEYS], Num] | None = None  # type: ignore[valid-type]
    tip_link: Name | None = None
    base_link: Name | None = None


class _Sigmas(Strict):
    """``errors.random`` entry selecting lengths and angles: one sigma for each."""

    length: NonNeg | None = None
    angle: NonNeg | None = None


class _Errors(Strict):
    explicit: dict[str, Num] | None = None
    random: dict[str, NonNeg | _Sigmas] | None = None


class _Mass(Strict):
    mass: NonNeg
    com: Vec3 = [0.0, 0.0, 0.0]


class _Payload(Strict):
    mass: NonNeg = 0.0
    com: Vec3 | None = None


PerJoint = dict[str, NonNeg]


class _Dynamics(Strict):
    inertia: NonNeg | PerJoint | None = None
    damping: NonNeg | PerJoint | None = None
    friction: NonNeg | PerJoint | None = None


class _Joints(Strict):
    backlash: PerJoint | None = None
    compliance: PerJoint | None = None
    masses: dict[str, _Mass] | None = None
    payload: NonNeg | _Payload | None = None
    gravity: Vec3 = [0.0, 0.0, -9.81]
    brakes: Literal["all", "none"] | list[str] = None  # type: ignore[assignment]
    dynamics: _Dynamics | None = None


class _Motion(Strict):
    time_mode: Literal["instant", "sim", "realtime"] = "instant"
    time_scale: Pos = 1.0
    start: list[Num] | None = Field(None, max_length=64)
    enabled: bool = True


class _Point(Strict):
    label: Name
    kind: Literal["socket", "needle"]
    position: Vec3
    approach: Vec3 = [0.0, 0.0, 1.0]
    radius: Pos = None  # type: ignore[assignment]


class _Cell(Strict):
    contact_radius: Pos = None  # type: ignore[assignment]
    capture_radius: Pos = None  # type: ignore[assignment]
    points: list[_Point] | None = Field(None, max_length=10_000)
    mounting: Any = None  # checked by station.kinematics.collision (the cell file's reader too)
    keep_out: Any = None
    collision: Literal["record", "stop"] = "record"


class _Noise(Strict):
    seating: NonNeg = None  # type: ignore[assignment]
    survey: NonNeg = 0.0
    encoder: NonNeg = 0.0
    positioning: NonNeg = 0.0


# a fault's wire trigger: the keys each emulator reports (station.mocks.world.faults.TRIGGERS), any value
_At = create_model("_At", __base__=Strict, after_s=(NonNeg, None),
                   **{wire: (create_model(f"_At_{wire}", __base__=Strict, **{k: (Any, None) for k in sorted(keys)})
                             | None, None) for wire, keys in TRIGGERS.items()})


class _Fault(Strict):
    do: Literal[FAULT_KINDS]  # type: ignore[valid-type]
    device: Any = None
    count: int = Field(1, ge=1)
    after: int = Field(0, ge=0)
    code: int | None = None
    at: _At | None = None  # type: ignore[valid-type]


class WorldSchema(Strict):
    """``station-world/1`` (docs/world.md)."""

    format: Literal["station-world/1"]
    units: _Units
    description: Any = ""
    seed: int = Field(0, ge=0)
    robot: _Robot | None = None
    errors: _Errors | None = None
    joints: _Joints | None = None
    motion: _Motion | None = None
    cell: _Cell | None = None
    noise: _Noise | None = None
    buses: dict[str, dict | None] | None = None  # each bus's settings: its emulator's (checked there)
    faults: list[_Fault] | None = None
