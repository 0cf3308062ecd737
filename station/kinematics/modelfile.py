"""Model files (YAML, ``format: station-model/1``): read with explicit units, write back. See docs/formats.md."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from station.kinematics.model import FRAME_AXES, Encoder, Joint, Model, from_dh, from_mdh, from_poe, screws_of
from station.kinematics.modelformat import ANGLE, ANGLE_KEYS, FORMAT, LENGTH, ModelFileError
from station.kinematics.modelformat import number as _num
from station.textfile import YamlDoc
from station.units import param_quantity

FRAME_KEYS = {"x", "y", "z", "rx", "ry", "rz"}


@dataclass(frozen=True)
class _Scale:
    """SI value of one file unit of length and of angle; which applies to a key is station.units' one rule."""

    length: float
    angle: float

    def of(self, key) -> float:
        return self.angle if param_quantity(str(key)) == "angle" else self.length

    def joint(self, revolute: bool) -> float:
        return self.angle if revolute else self.length


class _Reader:
    """Reads the parts of one model file into SI; every error names the file (``where``) and the field."""

    def __init__(self, where: str, scale: _Scale) -> None:
        self.where, self.scale = where, scale

    def frame(self, d, key: str) -> dict[str, float]:
        d = d or {}
        unknown = set(d) - FRAME_KEYS
        if unknown:
            raise ModelFileError(f"{self.where}: {key}: unknown keys {sorted(unknown)}")
        return {k: _num(v, f"{self.where}: {key}.{k}") * self.scale.of(k) for k, v in d.items()}

    def vec3(self, v, key: str, scale: float) -> np.ndarray:
        if not isinstance(v, list | tuple) or len(v) != 3:
            raise ModelFileError(f"{self.where}: {key}: expected [x, y, z], got {v!r}")
        return np.array([_num(x, f"{self.where}: {key}") * scale for x in v])

    def mass(self, v, key: str) -> float:
        m = _num(v, f"{self.where}: {key}")
        if m < 0:
            raise ModelFileError(f"{self.where}: {key}: a mass cannot be negative ({v!r})")
        return m

    def encoder(self, e: dict, w: str) -> Encoder:
        if "counts_per_rev" in e:
            cpu = _num(e["counts_per_rev"], f"{w}.encoder.counts_per_rev") / (2 * np.pi)
        elif "counts_per_m" in e:
            cpu = _num(e["counts_per_m"], f"{w}.encoder.counts_per_m")
        else:
            raise ModelFileError(f"{w}.encoder: needs counts_per_rev or counts_per_m")
        return Encoder(cpu, _num(e.get("gear", 1), f"{w}.encoder.gear"),
                       int(e.get("direction", 1)), _num(e.get("zero", 0), f"{w}.encoder.zero"))

    def joint(self, jd: dict, i: int, w: str) -> Joint:
        kind = jd.get("type", "revolute")
        if kind not in ("revolute", "prismatic"):
            raise ModelFileError(f"{w}.type: revolute or prismatic, got {kind!r}")
        U = self.scale.joint(kind == "revolute")
        lim = jd.get("limits")
        if not (isinstance(lim, list) and len(lim) == 2):
            raise ModelFileError(f"{w}.limits: expected [lower, upper]")
        lo, hi = (_num(x, f"{w}.limits") * U for x in lim)
        if lo >= hi:
            raise ModelFileError(f"{w}.limits: lower {lim[0]} is not below upper {lim[1]}")
        enc = self.encoder(jd["encoder"], w) if jd.get("encoder") else None
        return Joint(str(jd.get("name", f"j{i + 1}")), kind, lo, hi,
                     _num(jd.get("max_velocity", 1.0), f"{w}.max_velocity") * U,
                     _num(jd.get("max_acceleration", 10.0 / U), f"{w}.max_acceleration") * U, enc)

    def link(self, jd: dict, conv: str, revolute: bool, w: str) -> dict:
        """The joint's row of the dh/mdh table, or its screw (poe), in SI."""
        if conv in ("dh", "mdh"):
            g = jd.get(conv)
            if not isinstance(g, dict):
                raise ModelFileError(f"{w}: missing '{conv}' table")
            return {k: _num(v, f"{w}.{conv}.{k}") * self.scale.of(k) for k, v in g.items()}
        s = jd.get("screw")
        if not isinstance(s, dict) or "axis" not in s:
            raise ModelFileError(f"{w}: missing 'screw: {{axis: [..], point: [..]}}'")
        ax = np.array([_num(x, f"{w}.screw.axis") for x in s["axis"]])
        if ax.shape != (3,) or np.linalg.norm(ax) < 1e-9:
            raise ModelFileError(f"{w}.screw.axis: expected a non-zero 3-vector")
        sc = {"axis": ax / np.linalg.norm(ax)}
        if revolute:
            sc["point"] = np.array([_num(x, f"{w}.screw.point") * self.scale.length
                                    for x in s.get("point", [0, 0, 0])])
        return sc

    def payload(self, pd) -> tuple[float, np.ndarray] | None:
        if pd is None:
            return None
        if not isinstance(pd, dict) or set(pd) - {"mass", "com"} or "mass" not in pd:
            raise ModelFileError(f"{self.where}: payload: expected {{mass: kg, com: [x, y, z]}}, got {pd!r}")
        return self.mass(pd["mass"], "payload.mass"), self.vec3(pd.get("com", [0, 0, 0]), "payload.com",
                                                                self.scale.length)


@dataclass
class _Chain:
    """The per-joint parts of a model file, in SI, in joint order."""

    joints: list[Joint] = field(default_factory=list)
    links: list[dict] = field(default_factory=list)
    offsets: list[float] = field(default_factory=list)
    compliance: list[float] = field(default_factory=list)
    masses: dict[int, tuple[float, np.ndarray]] = field(default_factory=dict)


def _read_joints(r: _Reader, jdocs: list, conv: str) -> _Chain:
    out = _Chain()
    for i, jd in enumerate(jdocs):
        w = f"{r.where}: joints[{i}]"
        if not isinstance(jd, dict):
            raise ModelFileError(f"{w}: expected a mapping")
        joint = r.joint(jd, i, w)
        revolute = joint.kind == "revolute"
        out.joints.append(joint)
        out.offsets.append(_num(jd.get("offset", 0.0), f"{w}.offset") * r.scale.joint(revolute))
        c = _num(jd.get("compliance", 0.0), f"{w}.compliance") * r.scale.angle  # angle units per N m
        if c and not revolute:
            raise ModelFileError(f"{w}.compliance: only revolute joints have a gravity compliance")
        out.compliance.append(c)
        if "mass" in jd:
            out.masses[i + 1] = (r.mass(jd["mass"], f"joints[{i}].mass"),
                                 r.vec3(jd.get("com", [0, 0, 0]), f"joints[{i}].com", r.scale.length))
        elif "com" in jd:
            raise ModelFileError(f"{w}.com: given without a mass")
        out.links.append(r.link(jd, conv, revolute, w))
    return out


def _file_scale(doc: dict, where: str) -> tuple[_Scale, str]:
    """The file's stated units (no default: a bare number means nothing) and the length unit's name."""
    units = doc.get("units") or {}
    lu, au = units.get("length"), units.get("angle")
    if lu not in LENGTH or au not in ANGLE:
        raise ModelFileError(f"{where}: 'units' must state length (m|mm) and angle (rad|deg), got {units!r}")
    if units.get("mass", "kg") != "kg":
        raise ModelFileError(f"{where}: units.mass: only kg, got {units.get('mass')!r}")
    return _Scale(LENGTH[lu], ANGLE[au]), lu


def _checked_head(doc, ydoc: YamlDoc, where: str, shipped: bool) -> None:
    """Shape and format before any geometry: the strict schema (except for built-in models), then the head."""
    if not shipped and isinstance(doc, dict):
        from station.kinematics.modelschema import check_schema

        check_schema(ydoc, ModelFileError)
    if not isinstance(doc, dict):
        raise ModelFileError(f"{where}: not a mapping")
    if doc.get("format", FORMAT) != FORMAT:
        raise ModelFileError(f"{where}: format {doc.get('format')!r} is not {FORMAT!r}")
    if doc.get("kind", "serial") not in ("serial", "parallel"):
        raise ModelFileError(f"{where}: kind must be serial or parallel, got {doc['kind']!r}")


def model_from_dict(doc: dict | YamlDoc, where: str = "<model>", *, shipped: bool = False) -> Model:
    """The model of a parsed model file (a ``YamlDoc`` from ``station.yamlfile`` names lines in errors).

    ``shipped``: a built-in model (package data): its schema check ran in tests/cli/test_startup.py, so it is not
    repeated on every command (the schema is pydantic, ~0.1 s of start-up)."""
    if isinstance(doc, YamlDoc):
        ydoc, doc = doc, doc.data
    else:
        ydoc = YamlDoc(where, doc)
    _checked_head(doc, ydoc, where, shipped)
    if doc.get("kind", "serial") == "parallel":  # parallel robots: station/kinematics/parallelfile.py
        from station.kinematics.parallelfile import parallel_from_dict

        return parallel_from_dict(doc, where)
    scale, lu = _file_scale(doc, where)
    conv = doc.get("convention")
    if conv not in ("dh", "mdh", "poe"):
        raise ModelFileError(f"{where}: convention must be dh, mdh or poe, got {conv!r}")
    jdocs = doc.get("joints")
    if not isinstance(jdocs, list) or not jdocs:
        raise ModelFileError(f"{where}: 'joints' must be a non-empty list")
    r = _Reader(where, scale)
    chain = _read_joints(r, jdocs, conv)
    payload = r.payload(doc.get("payload"))
    grav = None if doc.get("gravity") is None else r.vec3(doc["gravity"], "gravity", 1.0)
    kw = dict(base=r.frame(doc.get("base"), "base"), tool=r.frame(doc.get("tool"), "tool"), offsets=chain.offsets,
              description=str(doc.get("description", "")), compliance=chain.compliance, masses=chain.masses,
              payload=payload, gravity_vector=grav)
    name = str(doc.get("name", Path(where).stem))
    _check_bounds(where, conv, chain.links, kw, chain.joints, chain.offsets, lu)
    if conv == "dh":
        model = from_dh(name, chain.joints, chain.links, **kw)
    elif conv == "mdh":
        model = from_mdh(name, chain.joints, chain.links, **kw)
    else:
        from station.kinematics.model import _pose

        model = from_poe(name, chain.joints, chain.links, _pose(r.frame(doc.get("home"), "home")), **kw)
    model = _with_collision(model, doc.get("collision"), f"{where}: collision", scale.length)
    return _with_tolerances(model, doc, where, scale.length, scale.angle)


MAX_LENGTH = 1000.0  # m: any one length of a robot (a kilometre is no robot: a typo or a unit slip)
MAX_ANGLE = 1000.0  # rad: any one angle (~160 turns)
MAX_REACH = 20.0  # m: all lengths of the chain added up; beyond it the numbers are not metres
MIN_REACH = 5e-3  # m: below it (with lengths at all) the numbers of a "mm" file are not millimetres


def _check_bounds(where: str, conv: str, links: list, kw: dict, joints: list, offsets: list, unit: str) -> None:
    """Every length and angle within physical bounds (one line naming the field), and the chain's reach plausible
    for the unit the file states: a UR5e written in millimetres under ``length: m`` reaches 1.3 km, the same
    numbers in metres under ``length: mm`` 1.3 mm; either is refused naming the likely unit."""

    for key, value, angle in _bounded_values(conv, links, kw, joints, offsets):
        bound, u = (MAX_ANGLE, "rad") if angle else (MAX_LENGTH, "m")
        if abs(value) > bound:
            raise ModelFileError(f"{where}: {key}: {value:.6g} {u} is beyond the physical bound of {bound:g} {u}")
    reach = _reach(links, kw)
    if reach > MAX_REACH:
        likely = "millimetres (write length: mm)" if unit == "m" else "not millimetres"
        raise ModelFileError(f"{where}: the chain reaches {_human_length(reach)} with these lengths (units: length: "
                             f"{unit}): no arm is that long; the numbers look like {likely}")
    if 0 < reach < MIN_REACH and unit == "mm":
        raise ModelFileError(f"{where}: the chain reaches {_human_length(reach)} with these lengths (units: length: "
                             f"mm): no arm is that small; the numbers look like metres (write length: m)")


def _bounded_values(conv: str, links: list, kw: dict, joints: list, offsets: list):
    """``(field, SI value, is an angle)`` of every number of the chain a physical bound applies to, in file
    order (a screw's axis is a direction: no bound)."""
    for i, link in enumerate(links):
        for k, v in link.items():
            if k == "point":
                yield from ((f"joints[{i}].screw.point", float(x), False) for x in v)
            elif k != "axis":
                yield f"joints[{i}].{conv}.{k}", v, k in ANGLE_KEYS
    for key in ("base", "tool"):
        yield from ((f"{key}.{k}", v, k in ANGLE_KEYS) for k, v in (kw.get(key) or {}).items())
    for i, (j, off) in enumerate(zip(joints, offsets, strict=True)):
        rev = j.kind == "revolute"
        yield from ((f"joints[{i}].limits", j.lower, rev), (f"joints[{i}].limits", j.upper, rev),
                    (f"joints[{i}].offset", off, rev))


def _reach(links: list, kw: dict) -> float:
    """All lengths of the chain added up (link lengths, the distances between screw points, the tool): an
    upper bound of how far the arm reaches, enough to tell metres from millimetres."""
    reach = 0.0
    for i, link in enumerate(links):
        for k, v in link.items():
            if k not in ("axis", "point") and k not in ANGLE_KEYS:
                reach += abs(v)
        if "point" in link and i:
            reach += float(np.linalg.norm(np.asarray(link["point"]) - np.asarray(links[i - 1].get("point", 0.0))))
    return reach + float(np.linalg.norm([(kw.get("tool") or {}).get(a, 0.0) for a in "xyz"]))


def _human_length(v: float) -> str:
    return f"{v / 1000:.4g} km" if v >= 1000 else f"{v:.4g} m" if v >= 1 else f"{v * 1000:.4g} mm"


def _with_collision(model: Model, c, where: str, L: float) -> Model:
    """The optional ``collision`` section: ``link_radii`` (one per joint: the capsule radius of the link that
    joint moves), ``tool_radius``, ``tool_free`` (the last part of the tool before the TCP, not checked: it
    touches the references); length units. Kept in ``model.source["collision"]`` in m."""
    if c is None:
        return model
    if not isinstance(c, dict) or set(c) - {"link_radii", "tool_radius", "tool_free"}:
        raise ModelFileError(f"{where}: expected a mapping of link_radii, tool_radius, tool_free")
    out = {}
    if "link_radii" in c:
        r = c["link_radii"]
        if not isinstance(r, list) or len(r) != model.n_joints:
            raise ModelFileError(f"{where}.link_radii: expected {model.n_joints} radii (one per joint)")
        out["link_radii"] = [_num(x, f"{where}.link_radii") * L for x in r]
    for key in ("tool_radius", "tool_free"):
        if key in c:
            out[key] = _num(c[key], f"{where}.{key}") * L
    if any(v < 0 for v in out.get("link_radii", []) + [out.get("tool_radius", 0), out.get("tool_free", 0)]):
        raise ModelFileError(f"{where}: radii and lengths must not be negative")
    return replace(model, source={**model.source, "collision": out})


def _with_tolerances(model: Model, doc: dict, where: str, L: float, A: float) -> Model:
    """``tolerances:`` (prior standard deviations for calibration), selectors checked against the model."""
    from station.kinematics.tolerances import parse_tolerances

    try:
        tols = parse_tolerances(doc.get("tolerances"), where, L, A)
        for sel, _, _ in tols:
            model.select([sel])
    except (ValueError, KeyError) as e:
        raise ModelFileError(f"{where}: tolerances: {e.args[0]}" if isinstance(e, KeyError) else str(e)) from None
    return replace(model, tolerances=tols) if tols else model


def load_model_file(path: str | Path) -> Model:
    from station.yamlfile import load_yaml_doc

    return model_from_dict(load_yaml_doc(path, ModelFileError), str(path))


def _r(x: float) -> float:
    return float(round(x, 12))  # a written model reads back to the same values, without float noise


def _joint_doc(model: Model, i: int, p: dict, L: float, A: float) -> dict:
    """Joint ``i``'s entry (limits, rates, encoder, offset, compliance, link mass) in file units."""
    j = model.joints[i]
    U = A if j.revolute else L
    jd: dict = {"name": j.name, "type": j.kind, "limits": [_r(j.lower * U), _r(j.upper * U)],
                "max_velocity": _r(j.max_velocity * U), "max_acceleration": _r(j.max_acceleration * U)}
    if j.encoder:
        e = j.encoder
        key, cpu = ("counts_per_rev", e.counts_per_unit * 2 * np.pi) if j.revolute else \
            ("counts_per_m", e.counts_per_unit)
        jd["encoder"] = {key: _r(cpu), "gear": _r(e.gear), "direction": e.direction, "zero": _r(e.zero)}
    jd["offset"] = _r(p[f"offset.j{i + 1}"] * U)
    if f"compliance.j{i + 1}" in p and (p[f"compliance.j{i + 1}"] or model.load is not None):
        jd["compliance"] = float(p[f"compliance.j{i + 1}"] * A)  # rad/(N m) -> angle units per N m
    if model.load is not None:
        mk, ck = model.load.link_mass(i + 1)
        if mk > 0:
            jd["mass"], jd["com"] = _r(mk), [_r(x * L) for x in ck]
    return jd


def _link_table(model: Model, i: int, p: dict, L: float, A: float) -> dict:
    """Joint ``i``'s dh/mdh row: the joint variable's own entry is its constant part, not a parameter."""
    c = model.convention
    k = int(np.flatnonzero(model.chain.joint == i)[0])
    const = float(model.chain.const[k])
    pre = f"{c}.j{i + 1}"
    tab = {"a": p[f"{pre}.a"] * L, "alpha": p[f"{pre}.alpha"] * A, "beta": p[f"{pre}.beta"] * A}
    if model.joints[i].revolute:
        tab |= {"d": p[f"{pre}.d"] * L, "theta": const * A}
    else:
        tab |= {"d": const * L, "theta": p[f"{pre}.theta"] * A}
    return {k2: _r(v) for k2, v in tab.items()}


def _screws_doc(model: Model, joints: list[dict], L: float, A: float) -> dict:
    """Each joint's screw (into ``joints``) and the ``home`` pose of a poe model, in file units."""
    from station.kinematics.se3 import matrix_to_rpy

    screws, home = screws_of(model)
    for i, s in enumerate(screws):
        joints[i]["screw"] = {"axis": [_r(x) for x in s["axis"]]}
        if "point" in s:
            joints[i]["screw"]["point"] = [_r(x * L) for x in s["point"]]
    rpy = matrix_to_rpy(home[:3, :3])
    return {"x": _r(home[0, 3] * L), "y": _r(home[1, 3] * L), "z": _r(home[2, 3] * L),
            "rx": _r(rpy[0] * A), "ry": _r(rpy[1] * A), "rz": _r(rpy[2] * A)}


def _extras_doc(model: Model, length: str, angle: str, L: float) -> dict:
    """The optional sections: tolerances, payload and gravity, collision."""
    doc: dict = {}
    if model.tolerances:
        from station.kinematics.tolerances import tolerances_to_doc

        doc["tolerances"] = tolerances_to_doc(model.tolerances, length, angle)
    if model.load is not None:
        pm, pc = model.load.payload
        if pm > 0:
            doc["payload"] = {"mass": _r(pm), "com": [_r(x * L) for x in pc]}
        doc["gravity"] = [_r(x) for x in model.load.gravity]
    col = model.source.get("collision")
    if col:
        doc["collision"] = {k: [_r(x * L) for x in v] if isinstance(v, list) else _r(v * L) for k, v in col.items()}
    return doc


def model_to_dict(model: Model, length: str = "m", angle: str = "rad") -> dict:
    """Current parameter values (nominal or calibrated) in the stated units."""
    if getattr(model, "kind", "serial") == "parallel":
        from station.kinematics.parallelfile import parallel_to_dict

        return parallel_to_dict(model, length, angle)
    L, A = 1 / LENGTH[length], 1 / ANGLE[angle]
    p = model.param_dict()

    def frame(prefix):
        return {k: _r(p[f"{prefix}.{k}"] * (A if param_quantity(k) == "angle" else L)) for k, _ in FRAME_AXES}

    joints = [_joint_doc(model, i, p, L, A) for i in range(len(model.joints))]
    doc: dict = {"format": FORMAT, "name": model.name, "description": model.description,
                 "convention": model.convention, "units": {"length": length, "angle": angle}}
    if model.convention in ("dh", "mdh"):
        for i in range(len(model.joints)):
            joints[i][model.convention] = _link_table(model, i, p, L, A)
    else:
        doc["home"] = _screws_doc(model, joints, L, A)
    doc["joints"] = joints
    doc["base"] = frame("base")
    doc["tool"] = frame("tcp")
    return doc | _extras_doc(model, length, angle, L)


def dump_model(model: Model, length: str = "m", angle: str = "rad") -> str:
    header = (f"# station kinematic model '{model.name}' ({model.convention.upper()}); "
              f"lengths in {length}, angles in {angle}, masses in kg, compliance in {angle} per N m, "
              f"gravity in m/s^2. Format: docs/formats.md\n")
    import yaml

    return header + yaml.safe_dump(model_to_dict(model, length, angle), sort_keys=False)
