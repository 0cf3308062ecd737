"""World files (YAML, ``format: station-world/1``): parse with explicit units into SI, write back.

The format is documented in docs/world.md. Every length is in ``units.length`` (m|mm), every angle in
``units.angle`` (rad|deg); time in s, mass in kg, joint compliance in ``units.angle`` per N*m, centres of
mass (link masses, payload) in ``units.length``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from station.mocks.errors import MockError
from station.mocks.world.cell import DEFAULTS, KINDS
from station.mocks.world.dynamics import JointDynamicsSpec

from station.kinematics.collision import KeepOut, KeepOutError, keep_out_from_dict, keep_out_to_doc
from station.units import ANGLE_UNITS, LENGTH_UNITS, joint_quantity, param_quantity

FORMAT = "station-world/1"
LENGTH = {u: LENGTH_UNITS[u] for u in ("m", "mm")}  # the units a world file may state
ANGLE = {u: ANGLE_UNITS[u] for u in ("rad", "deg")}
TIME_MODES = ("instant", "sim", "realtime")
SECTIONS = {"format", "units", "seed", "robot", "errors", "joints", "motion", "cell", "noise", "buses",
            "description", "faults"}

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


class _Reader:
    def __init__(self, where: str) -> None:
        self.where = where

    def fail(self, field_: str, msg: str) -> WorldFileError:
        return WorldFileError(f"{self.where}: {field_}: {msg}")

    def num(self, v, field_: str, *, positive: bool = False, nonneg: bool = False) -> float:
        if isinstance(v, bool | str):  # true is not 1; "1_0" and Arabic-Indic digits are not numbers
            raise self.fail(field_, f"expected a number, got {v!r}")
        try:
            x = float(v)
        except (TypeError, ValueError, OverflowError):
            raise self.fail(field_, f"expected a number, got {v!r}") from None
        if not math.isfinite(x):
            raise self.fail(field_, f"not a finite number ({v!r})")
        if positive and x <= 0:
            raise self.fail(field_, f"must be > 0, got {v!r}")
        if nonneg and x < 0:
            raise self.fail(field_, f"must be >= 0, got {v!r}")
        return x

    def mapping(self, v, field_: str, keys: set[str] | None = None) -> dict:
        if v is None:
            return {}
        if not isinstance(v, dict):
            raise self.fail(field_, f"expected a mapping, got {type(v).__name__}")
        if keys is not None:
            unknown = sorted(set(v) - keys)
            if unknown:
                raise self.fail(field_, f"unknown keys {unknown} (known: {sorted(keys)})")
        return v

    def vec3(self, v, field_: str, scale: float) -> list[float]:
        if not isinstance(v, list | tuple) or len(v) != 3:
            raise self.fail(field_, f"expected [x, y, z], got {v!r}")
        return [self.num(x, field_) * scale for x in v]


def _joint_index(model, key, r: _Reader, field_: str) -> int:
    names = [j.name for j in model.joints]
    k = str(key)
    if k in names:
        return names.index(k)
    if k.startswith("j") and k[1:].isdigit() and 1 <= int(k[1:]) <= model.n_joints:
        return int(k[1:]) - 1
    raise r.fail(field_, f"unknown joint {k!r} (use j1..j{model.n_joints} or {', '.join(names)})")


def spec_from_dict(doc, where: str = "<world>") -> WorldSpec:
    """The world of a parsed world file; ``WorldFileError`` (one line) for anything malformed."""
    try:
        return _spec_from_dict(doc, where)
    except WorldFileError:
        raise
    except (TypeError, KeyError, AttributeError, IndexError, ValueError, OverflowError) as e:
        # a shape the field checks above did not foresee (found by fuzzing): still one line, never a traceback
        raise WorldFileError(f"{where}: malformed world file ({type(e).__name__}: {str(e)[:120]})") from None


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


def _read_head(doc, r: _Reader) -> _Scale:
    """Format, known sections and the stated units (no default: a bare number means nothing)."""
    if not isinstance(doc, dict):
        raise WorldFileError(f"{r.where}: not a mapping (expected a station-world/1 document)")
    if doc.get("format") != FORMAT:
        raise r.fail("format", f"{doc.get('format')!r} is not {FORMAT!r}")
    unknown = sorted(set(doc) - SECTIONS)
    if unknown:
        raise r.fail(unknown[0], f"unknown section (known: {', '.join(sorted(SECTIONS))})")
    units = r.mapping(doc.get("units"), "units", {"length", "angle", "time", "mass"})
    if not all(isinstance(units.get(k), str) for k in ("length", "angle")) or units.get("length") not in LENGTH \
            or units.get("angle") not in ANGLE:
        raise r.fail("units", f"must state length (m|mm) and angle (rad|deg), got {units!r}")
    if units.get("time", "s") != "s" or units.get("mass", "kg") != "kg":
        raise r.fail("units", "time must be s and mass kg")
    return _Scale(LENGTH[units["length"]], ANGLE[units["angle"]])


def _read_robot(s: WorldSpec, robot: dict, r: _Reader, u: _Scale):
    """``robot:``: the model (a file next to the world file, a built-in name or a URDF chain) and its tool;
    the model, loaded."""
    from station.kinematics import ModelFileError, load_model

    s.model = str(robot.get("model", "ur5e"))
    s.tip_link = None if robot.get("tip_link") is None else str(robot["tip_link"])
    s.base_link = None if robot.get("base_link") is None else str(robot["base_link"])
    model_name = s.model
    if not Path(model_name).is_absolute() and r.where not in ("<world>",) and not _is_builtin(model_name):
        cand = Path(r.where).parent / model_name
        if cand.exists():
            s.model = str(cand.resolve())  # absolute: to_dict() output may be written elsewhere
    try:
        model = load_model(s.model, tip_link=s.tip_link, base_link=s.base_link)
    except ModelFileError as e:
        raise r.fail("robot.model", str(e)) from None
    if robot.get("tool") is not None:
        t = r.mapping(robot["tool"], "robot.tool", {"x", "y", "z", "rx", "ry", "rz"})
        s.tool = {k: r.num(v, f"robot.tool.{k}") * u.key(k) for k, v in t.items()}
    return model


def _read_explicit(s: WorldSpec, model, explicit, r: _Reader, u: _Scale) -> None:
    """``errors.explicit``: parameter -> its error, in the parameter's own unit."""
    for name, v in r.mapping(explicit, "errors.explicit").items():
        if name.startswith("compliance."):
            raise r.fail(f"errors.explicit.{name}", "the world's joint compliance is set in joints.compliance")
        if name not in model.param_names:
            raise r.fail(f"errors.explicit.{name}", f"no such parameter in model {model.name} "
                                                    f"(names like offset.j2, {model.param_names[7]}, tcp.z)")
        s.explicit[name] = r.num(v, f"errors.explicit.{name}") * u.of(param_kind(model, name))


def _random_sigmas(v, kinds: set[str], f: str, r: _Reader, u: _Scale) -> tuple[float | None, float | None]:
    """``(σ length, σ angle)`` of one ``errors.random`` entry selecting parameters of ``kinds``: one number
    when they are all of one quantity, ``{length: σ, angle: σ}`` when mixed."""
    if isinstance(v, dict):
        v = r.mapping(v, f, {"length", "angle"})
        sl = r.num(v["length"], f + ".length", nonneg=True) * u.length if "length" in v else None
        sa = r.num(v["angle"], f + ".angle", nonneg=True) * u.angle if "angle" in v else None
        missing = [k for k in kinds if (sl if k == "length" else sa) is None]
        if missing:
            raise r.fail(f, f"selects {missing[0]} parameters but gives no {missing[0]} sigma")
        return sl, sa
    if len(kinds) > 1:
        raise r.fail(f, "selects lengths and angles: give {length: sigma, angle: sigma}")
    x = r.num(v, f, nonneg=True)
    return (x * u.length, None) if kinds == {"length"} else (None, x * u.angle)


def _read_random(s: WorldSpec, model, random, r: _Reader, u: _Scale) -> None:
    """``errors.random``: selector -> sigma, drawn by the World from its seed."""
    for sel, v in r.mapping(random, "errors.random").items():
        f = f"errors.random.{sel}"
        try:
            names = model.select(str(sel))
        except KeyError as e:
            raise r.fail(f, str(e).strip("'\"")) from None
        if any(n.startswith("compliance.") for n in names):  # globs may sweep them in: the world's are elsewhere
            names = [n for n in names if not n.startswith("compliance.")]
            if not names:
                raise r.fail(f, "selects compliance parameters: the world's joint compliance is set in "
                                "joints.compliance")
        sl, sa = _random_sigmas(v, {param_kind(model, n) for n in names}, f, r, u)
        s.random.append((str(sel), sl, sa))


def _read_per_joint(s: WorldSpec, model, joints: dict, r: _Reader, u: _Scale) -> None:
    """``joints.backlash``, ``joints.compliance`` (in the joint's unit) and ``joints.masses``."""
    for k, v in r.mapping(joints.get("backlash"), "joints.backlash").items():
        i = _joint_index(model, k, r, f"joints.backlash.{k}")
        s.backlash[i] = r.num(v, f"joints.backlash.{k}", nonneg=True) * u.joint(model, i)
    for k, v in r.mapping(joints.get("compliance"), "joints.compliance").items():
        i = _joint_index(model, k, r, f"joints.compliance.{k}")
        s.compliance[i] = r.num(v, f"joints.compliance.{k}", nonneg=True) * u.joint(model, i)
    for k, v in r.mapping(joints.get("masses"), "joints.masses").items():
        i = _joint_index(model, k, r, f"joints.masses.{k}")
        v = r.mapping(v, f"joints.masses.{k}", {"mass", "com"})
        if "mass" not in v:
            raise r.fail(f"joints.masses.{k}", "expected {mass: kg, com: [x, y, z]}")
        s.masses[i + 1] = (r.num(v["mass"], f"joints.masses.{k}.mass", nonneg=True),
                           r.vec3(v.get("com", [0, 0, 0]), f"joints.masses.{k}.com", u.length))


def _read_joints(s: WorldSpec, model, joints, r: _Reader, u: _Scale) -> None:
    """``joints:``: brakes, free-joint dynamics, per-joint errors, the load (payload, gravity)."""
    joints = r.mapping(joints, "joints", {"backlash", "compliance", "payload", "gravity", "masses", "brakes",
                                          "dynamics"})
    if "brakes" in joints:
        s.brakes = _parse_brakes(model, joints["brakes"], r)
    if joints.get("dynamics") is not None:
        s.dynamics = _parse_dynamics(model, joints["dynamics"], r)
    _read_per_joint(s, model, joints, r, u)
    pay = joints.get("payload")
    if isinstance(pay, dict):
        pay = r.mapping(pay, "joints.payload", {"mass", "com"})
        if "com" in pay:
            s.payload_com = r.vec3(pay["com"], "joints.payload.com", u.length)
        pay = pay.get("mass", 0.0)
    if pay is not None:
        s.payload = r.num(pay, "joints.payload", nonneg=True)
    if "gravity" in joints:
        s.gravity = tuple(r.vec3(joints["gravity"], "joints.gravity", 1.0))


def _read_motion(s: WorldSpec, model, motion, r: _Reader, u: _Scale) -> None:
    """``motion:``: the clock, and where the arm starts (inside its joint limits)."""
    motion = r.mapping(motion, "motion", {"time_mode", "time_scale", "start", "enabled"})
    s.time_mode = str(motion.get("time_mode", "instant"))
    if s.time_mode not in TIME_MODES:
        raise r.fail("motion.time_mode", f"{s.time_mode!r} is not one of {', '.join(TIME_MODES)}")
    s.time_scale = r.num(motion.get("time_scale", 1.0), "motion.time_scale", positive=True)
    s.enabled = motion.get("enabled", True)
    if not isinstance(s.enabled, bool):
        raise r.fail("motion.enabled", f"expected true or false, got {s.enabled!r}")
    if motion.get("start") is not None:
        st = motion["start"]
        if not isinstance(st, list) or len(st) != model.n_joints:
            raise r.fail("motion.start", f"expected {model.n_joints} joint values, got {st!r}")
        s.start = [r.num(x, f"motion.start[{i}]") * u.joint(model, i) for i, x in enumerate(st)]
        lo, hi = model.lower, model.upper
        for i, x in enumerate(s.start):
            if not lo[i] <= x <= hi[i]:
                raise r.fail(f"motion.start[{i}]", f"outside the joint limits of {model.joints[i].name}")
    elif model.name in DEFAULTS:
        s.start = list(DEFAULTS[model.name]["start"])


def _read_point(p, f: str, labels: set[str], r: _Reader, u: _Scale) -> dict:
    """One reference point of ``cell.points`` (``f`` names it), positions in SI; its label joins ``labels``."""
    p = r.mapping(p, f, {"label", "kind", "position", "approach", "radius"})
    label = p.get("label", "")
    if not isinstance(label, str):  # null would become "None", 5 would become "5"
        raise r.fail(f + ".label", f"expected a text label, got {label!r}")
    if not label or label in labels:
        raise r.fail(f + ".label", f"missing or duplicate label {label!r}")
    labels.add(label)
    kind = p.get("kind")
    if kind not in KINDS:
        raise r.fail(f + ".kind", f"expected socket or needle, got {kind!r}")
    if "position" not in p:
        raise r.fail(f + ".position", "missing")
    ap = np.array(r.vec3(p.get("approach", [0, 0, 1]), f + ".approach", 1.0))
    if np.linalg.norm(ap) < 1e-9:
        raise r.fail(f + ".approach", "must be a non-zero vector")
    rad = r.num(p["radius"], f + ".radius", positive=True) * u.length if "radius" in p else None
    return {"label": label, "kind": kind, "position": r.vec3(p["position"], f + ".position", u.length),
            "approach": (ap / np.linalg.norm(ap)).tolist(), "radius": rad}


def _read_cell(s: WorldSpec, model, cell, r: _Reader, u: _Scale) -> None:
    """``cell:``: the true keep-out, contact and capture radii, the true reference points (default: the
    model's built-in cell)."""
    L = u.length
    cell = r.mapping(cell, "cell", {"contact_radius", "capture_radius", "points", "mounting", "keep_out",
                                    "collision"})
    s.collision = str(cell.get("collision", "record"))
    if s.collision not in ("record", "stop"):
        raise r.fail("cell.collision", f"expected record or stop, got {s.collision!r}")
    try:
        s.keep_out = keep_out_from_dict(cell, f"{r.where}: cell", L, u.angle, default_clearance=0.0)
    except KeepOutError as e:
        raise WorldFileError(str(e)) from None
    s.contact_radius = r.num(cell.get("contact_radius", CONTACT_RADIUS / L), "cell.contact_radius",
                             positive=True) * L
    s.capture_radius = r.num(cell.get("capture_radius", CAPTURE_RADIUS / L), "cell.capture_radius",
                             positive=True) * L
    pts = cell.get("points")
    if pts is None:
        pts = [dict(p, position=[x / L for x in p["position"]]) for p in DEFAULTS.get(model.name, {}).get(
            "points", [])]
    if not isinstance(pts, list):
        raise r.fail("cell.points", "expected a list of points")
    labels: set[str] = set()
    s.points.extend(_read_point(p, f"cell.points[{i}]", labels, r, u) for i, p in enumerate(pts))


def _read_noise(s: WorldSpec, noise, r: _Reader, u: _Scale) -> None:
    noise = r.mapping(noise, "noise", {"seating", "survey", "encoder", "positioning"})
    s.seating_sigma = r.num(noise.get("seating", SEATING_SIGMA / u.length), "noise.seating", nonneg=True) * u.length
    s.survey_sigma = r.num(noise.get("survey", 0.0), "noise.survey", nonneg=True) * u.length
    s.encoder_sigma = r.num(noise.get("encoder", 0.0), "noise.encoder", nonneg=True) * u.angle
    s.positioning_sigma = r.num(noise.get("positioning", 0.0), "noise.positioning", nonneg=True) * u.angle


def _spec_from_dict(doc, where: str) -> WorldSpec:
    r = _Reader(where)
    u = _read_head(doc, r)
    s = WorldSpec()
    s.description = str(doc.get("description", ""))
    seed = doc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise r.fail("seed", f"expected a non-negative integer, got {seed!r}")
    s.seed = seed
    model = _read_robot(s, r.mapping(doc.get("robot"), "robot", {"model", "tool", "tip_link", "base_link"}), r, u)
    errors = r.mapping(doc.get("errors"), "errors", {"explicit", "random"})
    _read_explicit(s, model, errors.get("explicit"), r, u)
    _read_random(s, model, errors.get("random"), r, u)
    _read_joints(s, model, doc.get("joints"), r, u)
    _read_motion(s, model, doc.get("motion"), r, u)
    _read_cell(s, model, doc.get("cell"), r, u)
    _read_noise(s, doc.get("noise"), r, u)
    buses = doc.get("buses") or {}
    if not isinstance(buses, dict) or any(not isinstance(v, dict | type(None)) for v in buses.values()):
        raise r.fail("buses", "expected a mapping of bus name -> settings mapping")
    s.buses = {str(k): dict(v or {}) for k, v in buses.items()}
    s.faults = _parse_faults(r, doc.get("faults"))
    return s


def _parse_brakes(model, v, r: _Reader) -> list[bool]:
    """``joints.brakes``: ``all``, ``none`` or a list of the joints that have one."""
    if v in ("all", "none"):
        return [v == "all"] * model.n_joints
    if not isinstance(v, list):
        raise r.fail("joints.brakes", f"expected all, none or a list of joints (j1.. or names), got {v!r}")
    out = [False] * model.n_joints
    for k in v:
        out[_joint_index(model, k, r, "joints.brakes")] = True
    return out


def _parse_dynamics(model, v, r: _Reader) -> JointDynamicsSpec:
    """``joints.dynamics``: ``{inertia, damping, friction}``, each a number for every joint or ``{joint: number}``,
    SI whatever ``units`` says (kg m^2, N m s/rad, N m; kg, N s/m, N for a prismatic joint)."""
    v = r.mapping(v, "joints.dynamics", {"inertia", "damping", "friction"})
    out = {}
    for key in ("inertia", "damping", "friction"):
        f = f"joints.dynamics.{key}"
        item = v.get(key)
        if item is None:
            out[key] = {}
        elif isinstance(item, dict):
            out[key] = {_joint_index(model, k, r, f"{f}.{k}"): r.num(x, f"{f}.{k}", nonneg=True)
                        for k, x in item.items()}
        else:
            x = r.num(item, f, nonneg=True)
            out[key] = dict.fromkeys(range(model.n_joints), x)
        if key == "inertia" and any(x <= 0 for x in out[key].values()):
            raise r.fail(f, "must be > 0")
    return JointDynamicsSpec(**out)


def _parse_faults(r, items) -> list[dict]:
    """``faults: [{do: timeout, device: 12, count: 1, after: 0, code: 0x20, at: {packet: {addr: 20}}}]``:
    ``do`` one of the emulators' fault kinds; ``at`` (optional) arms it only once an emulator sees a matching
    wire event (one of ``TRIGGERS``: ``packet: {addr: N}`` a Dynamixel write to address N, ``sdo: {index: 0x607C}``
    a CANopen SDO request, ``pdo: {cob_id: 0x201}`` a CANopen RPDO, ``rtde: {command: movej}`` /
    ``dashboard: {command: stop}`` / ``script: {program: rtde_control}`` on a UR controller) or ``after_s``
    seconds after start."""
    from station.mocks.world.faults import KINDS, TRIGGERS

    if items is None:
        return []
    if not isinstance(items, list):
        raise r.fail("faults", "expected a list of {do: KIND, device, count, after, code, at}")
    out = []
    for k, f in enumerate(items):
        where = f"faults[{k}]"
        f = r.mapping(f, where, {"do", "device", "count", "after", "code", "at"})
        kind = f.get("do")
        if kind not in KINDS:
            raise r.fail(f"{where}.do", f"{kind!r} is not one of {', '.join(KINDS)}")
        at = r.mapping(f.get("at") or {}, f"{where}.at", {"after_s", *TRIGGERS})
        for wire, keys in TRIGGERS.items():
            if wire in at:
                at[wire] = r.mapping(at[wire], f"{where}.at.{wire}", keys)
        if "after_s" in at:
            at["after_s"] = r.num(at["after_s"], f"{where}.at.after_s", nonneg=True)
        count, after = f.get("count", 1), f.get("after", 0)
        if not isinstance(count, int) or count < 1 or not isinstance(after, int) or after < 0:
            raise r.fail(where, f"count must be an integer >= 1 and after >= 0 (got {count!r}, {after!r})")
        code = f.get("code")
        if code is not None and not isinstance(code, int):
            raise r.fail(f"{where}.code", f"expected an integer error code, got {code!r}")
        out.append({"do": kind, "device": f.get("device"), "count": count, "after": after, "code": code,
                    "at": at})
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


def load_world_doc(path: str | Path) -> dict:
    from station.yamlfile import load_yaml

    return load_yaml(path, WorldFileError)
