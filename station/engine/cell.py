"""The station's view of the cell: where the fixed reference points are, as the integrator knows them.

File format (``station-cell/1``, YAML; written for emulated cells by ``station mock world cell WORLD``)::

    format: station-cell/1
    units: {length: mm, angle: deg}   # units of every position below (m or mm) and of tool angles
    model: ur5e                    # optional: the robot model this cell was laid out for
    tool: {x: 0, y: 0, z: 100, rx: 0, ry: 0, rz: 0}   # optional: nominal TCP of the mounted tool
    points:
      - {label: A, kind: socket, position: [450, 0, 50], approach: [0, 0, 1], radius: 3}

    distances:                     # optional: measured distances between points (length unit), for the solve
      - {between: [A, B], distance: 50.0, std: 0.01}   # std: its uncertainty (default 0.01 mm)
    planes: [P]                    # optional: labels whose touches lie on one (unknown) flat surface

    mounting: {normal: [0, 0, 1], offset: 0, clearance: 10}   # optional: the plane the arm stands on
    keep_out:                      # optional: volumes no link may enter (each keeps its clearance)
      - {name: fixture, box: {min: [300, -400, 0], max: [600, 400, 40]}}
      - {name: mast, box: {center: [0, 500, 400], size: [100, 100, 800], rotation: {rz: 30}}, clearance: 20}
      - {name: wall, plane: {point: [0, -600, 0], normal: [0, 1, 0]}}

``position`` is approximate, in the robot base frame; ``approach`` the unit vector from the point towards where
the tool comes from (up for a socket in a table); ``radius`` the socket capture / needle contact radius.
Without ``mounting`` the arm stands on the plane z = 0 of its base frame (10 mm clearance); ``mounting: none``
for an arm not standing on a plane. Format and semantics: docs/formats.md."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from station.kinematics.collision import Checker, KeepOut, KeepOutError, keep_out_from_dict
from station.robot.errors import ConfigError, LimitError
from station.strict import Name, NonNeg, Pos, Strict, Vec3, check
from station.units import ANGLE_UNITS, LENGTH_UNITS, param_quantity
from station.yamlfile import YamlDoc

FORMAT = "station-cell/1"
LENGTH = {u: LENGTH_UNITS[u] for u in ("m", "mm")}  # the units a cell file may state
ANGLE = {u: ANGLE_UNITS[u] for u in ("rad", "deg")}


class CellError(ConfigError):
    pass


@dataclass(frozen=True)
class RefPoint:
    label: str
    kind: str  # "socket" | "needle"
    position: np.ndarray  # m, robot base frame (approximate)
    approach: np.ndarray  # unit vector, point -> where the tool comes from
    radius: float = 0.002  # m
    image: str | None = None  # picture of the point for the operator's prompt (absolute path, checked at load)

    def to_dict(self) -> dict:
        d = {"label": self.label, "kind": self.kind, "position": self.position.tolist(),
             "approach": self.approach.tolist(), "radius": self.radius}
        return d if self.image is None else {**d, "image": self.image}

    @classmethod
    def from_dict(cls, d: dict) -> RefPoint:
        return cls(d["label"], d["kind"], np.asarray(d["position"], float), np.asarray(d["approach"], float),
                   float(d.get("radius", 0.002)), d.get("image"))


@dataclass(frozen=True)
class Cell:
    path: str
    points: dict[str, RefPoint]
    model: str | None = None
    tool: dict[str, float] | None = None  # nominal TCP on the flange (m, rad: x y z rx ry rz), if the cell says
    keep_out: KeepOut = field(default_factory=KeepOut.default)  # mounting plane + volumes no link may enter
    # known distances (label_a, label_b, metres, std metres or None: the solver's default) and plane labels:
    # what every solve of a procedure in this cell is told (station.solver.solve distances=, planes=)
    distances: list[tuple[str, str, float, float | None]] = field(default_factory=list)
    planes: list[str] = field(default_factory=list)

    def point(self, label: str) -> RefPoint:
        if label not in self.points:
            raise CellError(f"cell {self.path}: no reference point {label!r}; it has {', '.join(self.points)}")
        return self.points[label]

    def of_kind(self, kind: str) -> list[RefPoint]:
        return [p for p in self.points.values() if p.kind == kind]


# ---- schema (docs/formats.md): shapes, types, ranges; geometry and units are applied below ----
class _Units(Strict):
    length: Literal["m", "mm"]
    angle: Literal["rad", "deg"] = "rad"


class _Tool(Strict):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    rx: float = 0.0
    ry: float = 0.0
    rz: float = 0.0


class _PointBody(Strict):
    kind: Literal["socket", "needle"] = "socket"
    position: Vec3
    approach: Vec3 = [0.0, 0.0, 1.0]
    radius: Pos | None = None
    image: str | None = Field(None, min_length=1, max_length=1000)  # relative to the cell file


class _Point(_PointBody):
    label: Name


class _Distance(Strict):
    between: list[Name] = Field(min_length=2, max_length=2)
    distance: Pos
    std: Pos | None = None
    units: Literal["m", "mm"] | None = None  # default: the file's units.length


class _Cell(Strict):
    format: Literal["station-cell/1"]
    units: _Units
    frame: Literal["robot base"] = "robot base"  # the frame every position is in (written by the emulated cell)
    survey_sigma: NonNeg | None = None  # how well the positions were surveyed (length unit), informative
    model: Name | None = None
    tool: _Tool | None = None
    mounting: Any = None  # checked by station.kinematics.collision
    keep_out: Any = None
    distances: list[_Distance] | None = Field(default=None, max_length=10_000)
    planes: list[Name] | None = Field(default=None, max_length=10_000)


class CellSchema(_Cell):
    points: list[_Point] = Field(min_length=1, max_length=10_000)


class CellSchemaByLabel(_Cell):
    points: dict[Name, _PointBody] = Field(min_length=1, max_length=10_000)


def default_cell_path() -> Path:
    return Path(os.environ.get("STATION_CELL") or "cell.yaml")


def _vec(where: str, v, scale: float, unit: bool = False) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise CellError(f"{where}: expected 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise CellError(f"{where}: expected 3 finite numbers, got {v!r}")
    if unit:
        n = float(np.linalg.norm(a))
        if n < 1e-9:
            raise CellError(f"{where}: approach direction is zero")
        return a / n
    return a * scale


def load_cell(path: str | Path | None = None) -> Cell:
    from station.yamlfile import load_yaml_doc

    path = Path(path) if path else default_cell_path()
    doc = load_yaml_doc(path, CellError, "cell file", " (pass --cell FILE or set STATION_CELL)")
    return cell_from_dict(doc, str(path))


def _check_strict(ydoc: YamlDoc) -> None:
    """A ``cell/1`` document against the strict schema (file, line, field in the error); labels unique."""
    doc = ydoc.data
    check(CellSchemaByLabel if isinstance(doc.get("points"), dict) else CellSchema, ydoc, CellError)
    labels = [p.get("label") for p in doc["points"]] if isinstance(doc["points"], list) else []
    for i, lb in enumerate(labels):
        if lb in labels[:i]:
            raise CellError(f"{ydoc.where(('points', i, 'label'))}: label {lb!r} is used twice; labels name "
                            f"points and must be unique")


def _point(d, w: str, scale: float, where: str) -> RefPoint:
    """One reference point (``w`` names it in errors), positions in SI."""
    if not isinstance(d, dict) or "label" not in d:
        raise CellError(f"{w}: needs label, kind, position")
    kind = d.get("kind", "socket")
    if kind not in ("socket", "needle"):
        raise CellError(f"{w}: kind must be socket or needle, got {kind!r}")
    radius = d.get("radius", 2e-3 / scale)
    if not isinstance(radius, (int, float)) or not math.isfinite(radius) or radius <= 0:
        raise CellError(f"{w}: radius must be a positive number")
    label = str(d["label"])
    return RefPoint(label, kind, _vec(f"{w}.position", d.get("position"), scale),
                    _vec(f"{w}.approach", d.get("approach", [0, 0, 1]), 1.0, unit=True),
                    float(radius) * scale, _image(f"{w}.image", d.get("image"), where))


def _points(raw, where: str, scale: float) -> dict[str, RefPoint]:
    """``points:`` as a list of points or a mapping label -> point."""
    if isinstance(raw, dict):
        raw = [{"label": k, **(v or {})} for k, v in raw.items()]
    if not isinstance(raw, list) or not raw:
        raise CellError(f"{where}: 'points' must list at least one reference point")
    points: dict[str, RefPoint] = {}
    for i, d in enumerate(raw):
        pt = _point(d, f"{where}: points[{i}]", scale, where)
        points[pt.label] = pt
    return points


def _angle_unit(units, where: str) -> float:
    angle = ANGLE.get((units or {}).get("angle", "rad"))
    if angle is None:
        raise CellError(f"{where}: units.angle must be rad or deg")
    return angle


def _tool(tool, units, where: str, scale: float) -> dict[str, float] | None:
    """The optional tool frame, in SI (which keys are angles: station.units' one rule)."""
    if tool is None:
        return None
    if not isinstance(tool, dict) or set(tool) - {"x", "y", "z", "rx", "ry", "rz"}:
        raise CellError(f"{where}: tool must map x, y, z (length unit), rx, ry, rz (rad) to numbers")
    angle = _angle_unit(units, where)
    try:
        return {k: float(v) * (angle if param_quantity(k) == "angle" else scale) for k, v in tool.items()}
    except (TypeError, ValueError):
        raise CellError(f"{where}: tool values must be numbers") from None


def _distances(ydoc: YamlDoc, points: dict[str, RefPoint], scale: float) -> list:
    """Surveyed distances between points: ``(a, b, distance, std or None)`` in m."""
    distances = []
    for i, d in enumerate(ydoc.data.get("distances") or []):
        a, b = (str(x) for x in d["between"])
        if a == b:
            raise CellError(f"{ydoc.where(('distances', i, 'between'))}: the two points must differ")
        for lb in (a, b):
            if lb not in points:
                raise CellError(f"{ydoc.where(('distances', i, 'between'))}: no reference point {lb!r} "
                                f"(points: {', '.join(points)})")
        k = LENGTH[d["units"]] if d.get("units") else scale
        distances.append((a, b, float(d["distance"]) * k, None if d.get("std") is None else float(d["std"]) * k))
    return distances


def cell_from_dict(doc, where: str = "cell") -> Cell:
    """The cell of a parsed cell file (a ``YamlDoc`` names lines in errors)."""
    ydoc = doc if isinstance(doc, YamlDoc) else YamlDoc(where, doc)
    doc = ydoc.data
    if isinstance(doc, dict) and doc.get("format") == FORMAT:
        _check_strict(ydoc)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CellError(f"{where}: expected 'format: {FORMAT}'")
    units = doc.get("units") or {}
    length = units.get("length") if isinstance(units, dict) else None
    if length not in LENGTH:
        raise CellError(f"{where}: units.length must be m or mm (every position is in it), got {length!r}")
    scale = LENGTH[length]
    points = _points(doc.get("points"), where, scale)
    tool = _tool(doc.get("tool"), units, where, scale)
    angle = _angle_unit(units, where)
    distances = _distances(ydoc, points, scale)
    planes = [str(p) for p in doc.get("planes") or []]
    try:  # the one reader of mounting and keep_out (the world file's truth uses it too)
        keep_out = keep_out_from_dict(doc, where, scale, angle)
    except KeepOutError as e:
        raise CellError(str(e)) from None
    return Cell(where, points, doc.get("model"), tool, keep_out, distances, planes)


IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".gif": "image/gif",
               ".webp": "image/webp", ".svg": "image/svg+xml"}


def _image(w: str, image, cell_path: str) -> str | None:
    """A point's ``image:``: a picture file in the cell file's folder or below it (never outside: the panel
    serves it), of a type a browser shows; the absolute path."""
    if image is None:
        return None
    if not isinstance(image, str) or not image.strip():
        raise CellError(f"{w}: must be a file name relative to the cell file")
    rel = Path(image)
    if rel.is_absolute() or ".." in rel.parts:
        raise CellError(f"{w}: {image!r} must be relative to the cell file's folder and stay inside it")
    if rel.suffix.lower() not in IMAGE_TYPES:
        raise CellError(f"{w}: {image!r} is not a {', '.join(IMAGE_TYPES)} picture")
    folder = Path(cell_path).resolve().parent
    path = (folder / rel).resolve()
    if not path.is_relative_to(folder):  # a symlink pointing out of the folder
        raise CellError(f"{w}: {image!r} leads outside the cell file's folder")
    if not path.is_file():
        raise CellError(f"{w}: {image!r}: no such file {path}")
    return str(path)


# ---- keep-out ----------------------------------------------------------------------------------------------
def check_clear(model, keep_out: KeepOut | Cell | None, q, what: str = "target") -> None:
    """Refuse a joint target that brings a link capsule of ``model`` into a keep-out or within its clearance
    (``keep_out`` None: the default mounting plane). Raises ``LimitError`` naming the link and the obstacle."""
    ko = keep_out.keep_out if isinstance(keep_out, Cell) else keep_out
    hit = Checker(model, ko).hits(np.asarray(q, float)[None])[0]
    if hit is not None:
        raise LimitError(f"{what}: {hit.describe()}; refused")


def check_path_clear(model, keep_out: KeepOut | Cell | None, q_from, q_to, what: str = "move") -> None:
    """As :func:`check_clear` along the straight joint path ``q_from -> q_to`` (sampled so that no point of the
    arm moves more than 5 mm between checks)."""
    ko = keep_out.keep_out if isinstance(keep_out, Cell) else keep_out
    hit = Checker(model, ko).path_hit(q_from, q_to)
    if hit is not None:
        raise LimitError(f"{what}: {hit.describe()} on the way; refused")
