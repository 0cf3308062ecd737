"""World files (YAML, ``format: station-world/1``): parse with explicit units into SI, write back.

The format is documented in docs/world.md. Every length is in ``units.length`` (m|mm), every angle in
``units.angle`` (rad|deg); time in s, mass in kg, joint compliance in ``units.angle`` per N*m, centres of
mass (link masses, payload) in ``units.length``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from station.mocks.errors import MockError
from station.mocks.world.cell import DEFAULTS
from station.mocks.world.dynamics import JointDynamicsSpec

from station.kinematics.collision import KeepOut, KeepOutError, keep_out_from_dict, keep_out_to_doc
from station.textfile import YamlDoc
from station.units import ANGLE_UNITS, LENGTH_UNITS, joint_quantity, param_quantity

FORMAT = "station-world/1"
LENGTH = {u: LENGTH_UNITS[u] for u in ("m", "mm")}  # the units a world file may state
ANGLE = {u: ANGLE_UNITS[u] for u in ("rad", "deg")}
TIME_MODES = ("instant", "sim", "realtime")

# defaults (SI)
CONTACT_RADIUS = 50e-6
CAPTURE_RADIUS = 8e-3
SEATING_SIGMA = 10e-6


class WorldFileError(MockError, ValueError):
    """Malformed world file; the message names the file and the field. A ``MockError``, so the ``station``
    command prints it as one line and exits 2 wherever a world file is read."""


@dataclass
class WorldSpec:
    """A parsed world file, SI throughout. Random errors are kept as sigmas (drawn by the World)."""

    model: str = "ur5e"
    tip_link: str | None = None  # URDF model: chain end (default: the end of the only longest chain)
    base_link: str | None = None  # URDF model: chain start (default: the root)
    seed: int = 0
    description: str = ""
    tool: dict[str, float] | None = None  # nominal tool frame override {x,y,z,rx,ry,rz}
    explicit: dict[str, float] = field(default_factory=dict)  # parameter -> error (true - nominal)
    random: list[tuple[str, float | None, float | None]] = field(default_factory=list)  # (selector, σL, σA)
    backlash: dict[int, float] = field(default_factory=dict)  # joint index -> full width
    compliance: dict[int, float] = field(default_factory=dict)  # joint index -> rad/(N*m) or m/N
    masses: dict[int, tuple[float, list[float]]] = field(default_factory=dict)  # link k -> (kg, com in its frame)
    payload: float | None = None  # kg at the tool (None: the model's payload), loads the compliant joints
    payload_com: list[float] | None = None  # m, in the tool frame (default: the tool centre point)
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # m/s^2 in the base frame
    brakes: list[bool] | None = None  # per joint: a brake holds it when disabled (None: the device's default)
    dynamics: JointDynamicsSpec | None = None  # joints off their profiles (docs/world.md, "Free joints")
    start: list[float] | None = None
    enabled: bool = True
    time_mode: str = "instant"
    time_scale: float = 1.0
    contact_radius: float = CONTACT_RADIUS
    capture_radius: float = CAPTURE_RADIUS
    points: list[dict] = field(default_factory=list)  # label, kind, position, approach, radius|None
    seating_sigma: float = SEATING_SIGMA
    survey_sigma: float = 0.0
    encoder_sigma: float = 0.0
    positioning_sigma: float = 0.0  # per joint, per move: where the link ends vs where the encoder says (SI)
    buses: dict = field(default_factory=dict)
    faults: list[dict] = field(default_factory=list)  # armed at start: {do, device, count, after, code, at}
    keep_out: KeepOut = field(default_factory=lambda: KeepOut.default(0.0))  # truth: contact is a collision
    collision: str = "record"  # a link touching a keep-out: "record" it (world.collisions) or also "stop"


def param_kind(model, name: str) -> str:
    """``"length"``, ``"angle"`` (station.units' one rule for a parameter of ``model``) or ``"compliance"``
    (the world sets joint compliance in ``joints.compliance``, not as a parameter error)."""
    if name.startswith("compliance."):
        return "compliance"
    return param_quantity(name, model)


@dataclass(frozen=True)
class _Reader:
    """Where each value of a schema-checked world file is (its line), for the checks the schema cannot make:
    the model's own joint and parameter names, limits, labels."""

    doc: YamlDoc

    def fail(self, path: tuple, msg: str) -> WorldFileError:
        return WorldFileError(f"{self.doc.where(path)}: {msg}")


def _vec3(v, scale: float) -> list[float]:
    return [float(x) * scale for x in v]


def _joint_index(model, key, r: _Reader, path: tuple) -> int:
    names = [j.name for j in model.joints]
    k = str(key)
    if k in names:
        return names.index(k)
    if k.startswith("j") and k[1:].isdigit() and 1 <= int(k[1:]) <= model.n_joints:
        return int(k[1:]) - 1
    raise r.fail(path, f"unknown joint {k!r} (use j1..j{model.n_joints} or {', '.join(names)})")


def spec_from_dict(doc, where: str = "<world>") -> WorldSpec:
    """The world of a parsed world file (a ``YamlDoc`` from ``station.yamlfile`` names lines in errors);
    ``WorldFileError`` (one line: file, line, field) for anything malformed."""
    ydoc = doc if isinstance(doc, YamlDoc) else YamlDoc(where, doc)
    try:
        return _spec_from_dict(ydoc)
    except WorldFileError:
        raise
    except (TypeError, KeyError, AttributeError, IndexError, ValueError, OverflowError) as e:
        # a shape the checks did not foresee (found by fuzzing): still one line, never a traceback
        raise WorldFileError(f"{ydoc.name}: malformed world file ({type(e).__name__}: {str(e)[:120]})") from None


@dataclass(frozen=True)
class _Scale:
    """SI value of one file unit of length and of angle; which one a value takes is station.units' one rule."""

    length: float
    angle: float

    def of(self, quantity: str) -> float:
        return {"length": self.length, "angle": self.angle}[quantity]

    def key(self, key: str) -> float:
        """A frame's key (x, y, z, rx, ry, rz)."""
        return self.of(param_quantity(key))

    def joint(self, model, i: int) -> float:
        """A value of joint ``i`` (its limits, backlash, compliance): an angle or a length by the joint's kind."""
        return self.of(joint_quantity(model.joints[i].revolute))


def _read_head(r: _Reader) -> _Scale:
    """Format, then the strict schema (every section's keys, types and ranges), then the stated units (no
    default: a bare number means nothing)."""
    from station.mocks.world.worldschema import WorldSchema

    from station.strict import check

    doc = r.doc.data
    if not isinstance(doc, dict):
        raise WorldFileError(f"{r.doc.name}: not a mapping (expected a {FORMAT} document)")
    if doc.get("format") != FORMAT:
        raise r.fail(("format",), f"{doc.get('format')!r} is not {FORMAT!r}")
    check(WorldSchema, r.doc, WorldFileError)
    return _Scale(LENGTH[doc["units"]["length"]], ANGLE[doc["units"]["angle"]])


def _read_robot(s: WorldSpec, robot: dict, r: _Reader, u: _Scale):
    """``robot:``: the model (a file next to the world file, a built-in name or a URDF chain) and its tool;
    the model, loaded."""
    from station.kinematics import ModelFileError, load_model

    s.model = str(robot.get("model", "ur5e"))
    s.tip_link = robot.get("tip_link")
    s.base_link = robot.get("base_link")
    where = r.doc.name
    if not Path(s.model).is_absolute() and not where.startswith("<") and not _is_builtin(s.model):
        cand = Path(where).parent / s.model
        if cand.exists():
            s.model = str(cand.resolve())  # absolute: to_dict() output may be written elsewhere
    try:
        model = load_model(s.model, tip_link=s.tip_link, base_link=s.base_link)
    except ModelFileError as e:
        raise r.fail(("robot", "model"), str(e)) from None
    if robot.get("tool") is not None:
        s.tool = {k: float(v) * u.key(k) for k, v in robot["tool"].items()}
    return model


def _read_explicit(s: WorldSpec, model, explicit: dict, r: _Reader, u: _Scale) -> None:
    """``errors.explicit``: parameter -> its error, in the parameter's own unit."""
    for name, v in explicit.items():
        path = ("errors", "explicit", name)
        if name.startswith("compliance."):
            raise r.fail(path, "the world's joint compliance is set in joints.compliance")
        if name not in model.param_names:
            raise r.fail(path, f"no such parameter in model {model.name} "
                               f"(names like offset.j2, {model.param_names[7]}, tcp.z)")
        s.explicit[name] = float(v) * u.of(param_kind(model, name))


def _random_sigmas(v, kinds: set[str], path: tuple, r: _Reader, u: _Scale) -> tuple[float | None, float | None]:
    """``(σ length, σ angle)`` of one ``errors.random`` entry selecting parameters of ``kinds``: one number
    when they are all of one quantity, ``{length: σ, angle: σ}`` when mixed."""
    if isinstance(v, dict):
        sl = float(v["length"]) * u.length if v.get("length") is not None else None
        sa = float(v["angle"]) * u.angle if v.get("angle") is not None else None
        missing = [k for k in kinds if (sl if k == "length" else sa) is None]
        if missing:
            raise r.fail(path, f"selects {missing[0]} parameters but gives no {missing[0]} sigma")
        return sl, sa
    if len(kinds) > 1:
        raise r.fail(path, "selects lengths and angles: give {length: sigma, angle: sigma}")
    return (float(v) * u.length, None) if kinds == {"length"} else (None, float(v) * u.angle)


def _read_random(s: WorldSpec, model, random: dict, r: _Reader, u: _Scale) -> None:
    """``errors.random``: selector -> sigma, drawn by the World from its seed."""
    for sel, v in random.items():
        path = ("errors", "random", sel)
        try:
            names = model.select(sel)
        except KeyError as e:
            raise r.fail(path, str(e).strip("'\"")) from None
        if any(n.startswith("compliance.") for n in names):  # globs may sweep them in: the world's are elsewhere
            names = [n for n in names if not n.startswith("compliance.")]
            if not names:
                raise r.fail(path, "selects compliance parameters: the world's joint compliance is set in "
                                   "joints.compliance")
        sl, sa = _random_sigmas(v, {param_kind(model, n) for n in names}, path, r, u)
        s.random.append((sel, sl, sa))


def _read_per_joint(s: WorldSpec, model, joints: dict, r: _Reader, u: _Scale) -> None:
    """``joints.backlash``, ``joints.compliance`` (in the joint's unit) and ``joints.masses``."""
    for k, v in (joints.get("backlash") or {}).items():
        i = _joint_index(model, k, r, ("joints", "backlash", k))
        s.backlash[i] = float(v) * u.joint(model, i)
    for k, v in (joints.get("compliance") or {}).items():
        i = _joint_index(model, k, r, ("joints", "compliance", k))
        s.compliance[i] = float(v) * u.joint(model, i)
    for k, v in (joints.get("masses") or {}).items():
        i = _joint_index(model, k, r, ("joints", "masses", k))
        s.masses[i + 1] = (float(v["mass"]), _vec3(v.get("com", [0, 0, 0]), u.length))


def _read_joints(s: WorldSpec, model, joints: dict, r: _Reader, u: _Scale) -> None:
    """``joints:``: brakes, free-joint dynamics, per-joint errors, the load (payload, gravity)."""
    if "brakes" in joints:
        s.brakes = _parse_brakes(model, joints["brakes"], r)
    if joints.get("dynamics") is not None:
        s.dynamics = _parse_dynamics(model, joints["dynamics"], r)
    _read_per_joint(s, model, joints, r, u)
    pay = joints.get("payload")
    if isinstance(pay, dict):
        if pay.get("com") is not None:
            s.payload_com = _vec3(pay["com"], u.length)
        pay = pay.get("mass", 0.0)
    if pay is not None:
        s.payload = float(pay)
    if "gravity" in joints:
        s.gravity = tuple(_vec3(joints["gravity"], 1.0))


def _read_motion(s: WorldSpec, model, motion: dict, r: _Reader, u: _Scale) -> None:
    """``motion:``: the clock, and where the arm starts (inside its joint limits)."""
    s.time_mode = motion.get("time_mode", "instant")
    s.time_scale = float(motion.get("time_scale", 1.0))
    s.enabled = motion.get("enabled", True)
    st = motion.get("start")
    if st is not None:
        if len(st) != model.n_joints:
            raise r.fail(("motion", "start"), f"expected {model.n_joints} joint values, got {st!r}")
        s.start = [float(x) * u.joint(model, i) for i, x in enumerate(st)]
        lo, hi = model.lower, model.upper
        for i, x in enumerate(s.start):
            if not lo[i] <= x <= hi[i]:
                raise r.fail(("motion", "start", i), f"outside the joint limits of {model.joints[i].name}")
    elif model.name in DEFAULTS:
        s.start = list(DEFAULTS[model.name]["start"])


def _read_point(p: dict, path: tuple, labels: set[str], r: _Reader, u: _Scale) -> dict:
    """One reference point of ``cell.points`` (``path`` names it), positions in SI; its label joins ``labels``."""
    label = p["label"]
    if label in labels:
        raise r.fail(path + ("label",), f"duplicate label {label!r} (labels name points and must be unique)")
    labels.add(label)
    ap = np.array(_vec3(p.get("approach", [0, 0, 1]), 1.0))
    if np.linalg.norm(ap) < 1e-9:
        raise r.fail(path + ("approach",), "must be a non-zero vector")
    rad = float(p["radius"]) * u.length if "radius" in p else None
    return {"label": label, "kind": p["kind"], "position": _vec3(p["position"], u.length),
            "approach": (ap / np.linalg.norm(ap)).tolist(), "radius": rad}


def _read_cell(s: WorldSpec, model, cell: dict, r: _Reader, u: _Scale) -> None:
    """``cell:``: the true keep-out, contact and capture radii, the true reference points (default: the
    model's built-in cell)."""
    L = u.length
    s.collision = cell.get("collision", "record")
    try:  # the one reader of mounting and keep_out (the cell file's too)
        s.keep_out = keep_out_from_dict(cell, r.doc.where(("cell",)), L, u.angle, default_clearance=0.0)
    except KeepOutError as e:
        raise WorldFileError(str(e)) from None
    s.contact_radius = float(cell.get("contact_radius", CONTACT_RADIUS / L)) * L
    s.capture_radius = float(cell.get("capture_radius", CAPTURE_RADIUS / L)) * L
    pts = cell.get("points")
    if pts is None:  # the model's built-in cell, written in the file's unit as if the file had it
        pts = [dict(p, position=[x / L for x in p["position"]]) for p in DEFAULTS.get(model.name, {}).get(
            "points", [])]
    labels: set[str] = set()
    s.points.extend(_read_point(p, ("cell", "points", i), labels, r, u) for i, p in enumerate(pts))


def _read_noise(s: WorldSpec, noise: dict, u: _Scale) -> None:
    s.seating_sigma = float(noise.get("seating", SEATING_SIGMA / u.length)) * u.length
    s.survey_sigma = float(noise.get("survey", 0.0)) * u.length
    s.encoder_sigma = float(noise.get("encoder", 0.0)) * u.angle
    s.positioning_sigma = float(noise.get("positioning", 0.0)) * u.angle


def _spec_from_dict(ydoc: YamlDoc) -> WorldSpec:
    r = _Reader(ydoc)
    u = _read_head(r)
    doc = ydoc.data
    s = WorldSpec(description=str(doc.get("description", "")), seed=doc.get("seed", 0))
    model = _read_robot(s, doc.get("robot") or {}, r, u)
    errors = doc.get("errors") or {}
    _read_explicit(s, model, errors.get("explicit") or {}, r, u)
    _read_random(s, model, errors.get("random") or {}, r, u)
    _read_joints(s, model, doc.get("joints") or {}, r, u)
    _read_motion(s, model, doc.get("motion") or {}, r, u)
    _read_cell(s, model, doc.get("cell") or {}, r, u)
    _read_noise(s, doc.get("noise") or {}, u)
    s.buses = {k: dict(v or {}) for k, v in (doc.get("buses") or {}).items()}
    s.faults = _read_faults(doc.get("faults") or [])
    return s


def _parse_brakes(model, v, r: _Reader) -> list[bool]:
    """``joints.brakes``: ``all``, ``none`` or a list of the joints that have one."""
    if v in ("all", "none"):
        return [v == "all"] * model.n_joints
    out = [False] * model.n_joints
    for i, k in enumerate(v):
        out[_joint_index(model, k, r, ("joints", "brakes", i))] = True
    return out


def _parse_dynamics(model, v: dict, r: _Reader) -> JointDynamicsSpec:
    """``joints.dynamics``: ``{inertia, damping, friction}``, each a number for every joint or ``{joint: number}``,
    SI whatever ``units`` says (kg m^2, N m s/rad, N m; kg, N s/m, N for a prismatic joint)."""
    out = {}
    for key in ("inertia", "damping", "friction"):
        path = ("joints", "dynamics", key)
        item = v.get(key)
        if item is None:
            out[key] = {}
        elif isinstance(item, dict):
            out[key] = {_joint_index(model, k, r, path + (k,)): float(x) for k, x in item.items()}
        else:
            out[key] = dict.fromkeys(range(model.n_joints), float(item))
        if key == "inertia" and any(x <= 0 for x in out[key].values()):
            raise r.fail(path, "must be > 0")
    return JointDynamicsSpec(**out)


def _read_faults(items: list) -> list[dict]:
    """``faults: [{do: timeout, device: 12, count: 1, after: 0, code: 0x20, at: {packet: {addr: 20}}}]``:
    ``do`` one of the emulators' fault kinds; ``at`` (optional) arms it only once an emulator sees a matching
    wire event (one of ``TRIGGERS``: ``packet: {addr: N}`` a Dynamixel write to address N, ``sdo: {index: 0x607C}``
    a CANopen SDO request, ``pdo: {cob_id: 0x201}`` a CANopen RPDO, ``rtde: {command: movej}`` /
    ``dashboard: {command: stop}`` / ``script: {program: rtde_control}`` on a UR controller) or ``after_s``
    seconds after start. Shapes and kinds: the schema (worldschema.py)."""
    out = []
    for f in items:
        at = {k: (float(v) if k == "after_s" else dict(v or {})) for k, v in (f.get("at") or {}).items()}
        out.append({"do": f["do"], "device": f.get("device"), "count": f.get("count", 1), "after": f.get("after", 0),
                    "code": f.get("code"), "at": at})
    return out


def _is_builtin(name: str) -> bool:
    from station.kinematics import builtin_names

    return name in builtin_names()


def spec_to_dict(s: WorldSpec, model, length: str = "m", angle: str = "rad") -> dict:
    """The spec as a world document in the given units (loads back to the same world)."""
    L, A = 1 / LENGTH[length], 1 / ANGLE[angle]
    U = {"length": L, "angle": A}

    def jscale(i):
        return U[joint_quantity(model.joints[i].revolute)]

    def r(x):
        return float(round(x, 12))

    doc: dict = {"format": FORMAT, "description": s.description,
                 "units": {"length": length, "angle": angle, "time": "s", "mass": "kg"}, "seed": s.seed}
    robot: dict = {"model": s.model}
    robot.update({k: v for k, v in (("tip_link", s.tip_link), ("base_link", s.base_link)) if v is not None})
    if s.tool:
        robot["tool"] = {k: r(v * U[param_quantity(k)]) for k, v in s.tool.items()}
    doc["robot"] = robot
    random: dict = {}
    for sel, sl, sa in s.random:
        kinds = {param_kind(model, n) for n in model.select(sel)}
        if len(kinds) == 1:
            random[sel] = r((sl if kinds == {"length"} else sa) * U[kinds.pop()])
        else:
            # the sigmas the file gave (a selector may select nothing on this model: no quantity to infer)
            random[sel] = {k: r(v * f) for k, v, f in (("length", sl, L), ("angle", sa, A)) if v is not None}
    doc["errors"] = {"explicit": {n: r(v * U[param_kind(model, n)]) for n, v in s.explicit.items()},
                     "random": random}
    doc["joints"] = {"backlash": {f"j{i + 1}": r(v * jscale(i)) for i, v in s.backlash.items()},
                     "compliance": {f"j{i + 1}": r(v * jscale(i)) for i, v in s.compliance.items()},
                     "gravity": [r(g) for g in s.gravity]}
    if s.masses:
        doc["joints"]["masses"] = {f"j{k}": {"mass": r(m), "com": [r(x * L) for x in c]}
                                   for k, (m, c) in s.masses.items()}
    if s.brakes is not None:
        doc["joints"]["brakes"] = [f"j{i + 1}" for i, b in enumerate(s.brakes) if b]
    if s.dynamics is not None:
        doc["joints"]["dynamics"] = {k: {f"j{i + 1}": r(x) for i, x in getattr(s.dynamics, k).items()}
                                     for k in ("inertia", "damping", "friction")}
    if s.payload is not None:
        doc["joints"]["payload"] = (r(s.payload) if s.payload_com is None else
                                    {"mass": r(s.payload), "com": [r(x * L) for x in s.payload_com]})
    motion: dict = {"time_mode": s.time_mode, "time_scale": r(s.time_scale), "enabled": s.enabled}
    if s.start is not None:
        motion["start"] = [r(x * jscale(i)) for i, x in enumerate(s.start)]
    doc["motion"] = motion
    pts = []
    for p in s.points:
        d = {"label": p["label"], "kind": p["kind"], "position": [r(x * L) for x in p["position"]],
             "approach": [r(x) for x in p["approach"]]}
        if p.get("radius") is not None:
            d["radius"] = r(p["radius"] * L)
        pts.append(d)
    doc["cell"] = {"contact_radius": r(s.contact_radius * L), "capture_radius": r(s.capture_radius * L),
                   "points": pts, **keep_out_to_doc(s.keep_out, 1 / L, 1 / A),
                   "collision": s.collision}
    doc["noise"] = {"seating": r(s.seating_sigma * L), "survey": r(s.survey_sigma * L),
                    "encoder": r(s.encoder_sigma * A), "positioning": r(s.positioning_sigma * A)}
    doc["buses"] = s.buses
    if s.faults:
        doc["faults"] = s.faults
    return doc


def load_world_doc(path: str | Path) -> YamlDoc:
    """The parsed world file with the line of every field (for the reader's errors)."""
    from station.yamlfile import load_yaml_doc

    return load_yaml_doc(path, WorldFileError)
