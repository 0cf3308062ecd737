"""The ``kind: parallel`` branch of ``station-model/1`` files (docs/formats.md): read with explicit units, write
back. Errors name the file and the field in one line."""

from __future__ import annotations

import numpy as np

from station.kinematics.model import Encoder
from station.kinematics.modelformat import ANGLE, FORMAT, LENGTH, ModelFileError
from station.kinematics.modelformat import number as _num
from station.kinematics.parallel import (
    GOUGH_STEWART,
    PLANAR_STRUTS,
    TYPES,
    ParallelModel,
    gough_stewart,
    planar_struts,
)

POSE_KEYS = ("x", "y", "z", "rx", "ry", "rz")


def _points(v, n: int, dim: int, where: str, L: float) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        raise ModelFileError(f"{where}: expected {n} points [{', '.join('xyz'[:dim])}], got "
                             f"{'a list of ' + str(len(v)) if isinstance(v, list) else repr(v)}")
    out = np.zeros((n, dim))
    for k, p in enumerate(v):
        if not isinstance(p, list) or len(p) != dim:
            raise ModelFileError(f"{where}[{k}]: expected [{', '.join('xyz'[:dim])}], got {p!r}")
        out[k] = [_num(x, f"{where}[{k}]") * L for x in p]
    return out


def _limits(v, n: int, where: str, L: float) -> np.ndarray:
    """One ``[lo, hi]`` for every actuator or one per actuator."""
    if isinstance(v, list) and len(v) == 2 and not isinstance(v[0], list):
        v = [v] * n
    if not isinstance(v, list) or len(v) != n:
        raise ModelFileError(f"{where}: expected [lo, hi] or {n} of them")
    out = np.zeros((n, 2))
    for k, lim in enumerate(v):
        if not isinstance(lim, list) or len(lim) != 2:
            raise ModelFileError(f"{where}[{k}]: expected [lo, hi], got {lim!r}")
        lo, hi = (_num(x, f"{where}[{k}]") * L for x in lim)
        if not 0 < lo < hi:
            raise ModelFileError(f"{where}[{k}]: need 0 < lower < upper, got {lim!r}")
        out[k] = lo, hi
    return out


def _pose(d, where: str, L: float, A: float, required: bool) -> dict[str, float]:
    if d is None and not required:
        return {}
    if not isinstance(d, dict):
        raise ModelFileError(f"{where}: expected {{x, y, z, rx, ry, rz}}")
    unknown = sorted(set(d) - set(POSE_KEYS))
    if unknown:
        raise ModelFileError(f"{where}: unknown keys {unknown}")
    return {k: _num(v, f"{where}.{k}") * (A if k.startswith("r") else L) for k, v in d.items()}


def _actuators(d, n: int, where: str, L: float) -> dict:
    """``legs:``/``struts:`` mapping: limits, optional offsets, max_velocity, max_acceleration, encoder."""
    if not isinstance(d, dict) or "limits" not in d:
        raise ModelFileError(f"{where}: expected {{limits: [lo, hi]}}")
    unknown = sorted(set(d) - {"limits", "offsets", "max_velocity", "max_acceleration", "encoder"})
    if unknown:
        raise ModelFileError(f"{where}: unknown keys {unknown}")
    out: dict = {"limits": _limits(d["limits"], n, f"{where}.limits", L)}
    if "offsets" in d:
        offs = d["offsets"]
        if not isinstance(offs, list) or len(offs) != n:
            raise ModelFileError(f"{where}.offsets: expected {n} numbers")
        out["offsets"] = [_num(x, f"{where}.offsets[{k}]") * L for k, x in enumerate(offs)]
    for key in ("max_velocity", "max_acceleration"):
        if key in d:
            out[key] = _num(d[key], f"{where}.{key}") * L
            if out[key] <= 0:
                raise ModelFileError(f"{where}.{key}: must be > 0")
    if d.get("encoder") is not None:
        e = d["encoder"]
        if not isinstance(e, dict) or "counts_per_m" not in e:
            raise ModelFileError(f"{where}.encoder: needs counts_per_m (counts per metre of leg travel)")
        unknown = sorted(map(str, set(e) - {"counts_per_m", "gear", "direction", "zero"}))
        if unknown:
            raise ModelFileError(f"{where}.encoder: unknown keys {unknown}")
        cpm = _num(e["counts_per_m"], f"{where}.encoder.counts_per_m")
        gear = _num(e.get("gear", 1), f"{where}.encoder.gear")
        direction = e.get("direction", 1)
        if cpm <= 0 or gear <= 0:
            raise ModelFileError(f"{where}.encoder: counts_per_m and gear must be > 0 (the sign is the direction's)")
        if isinstance(direction, bool) or direction not in (1, -1):
            raise ModelFileError(f"{where}.encoder.direction: must be 1 or -1, got {direction!r}")
        out["encoder"] = Encoder(cpm, gear, int(direction), _num(e.get("zero", 0), f"{where}.encoder.zero"))
    return out


def parallel_from_dict(doc: dict, where: str = "<model>") -> ParallelModel:
    """A ``kind: parallel`` model document (the caller has checked ``format``)."""
    units = doc.get("units") or {}
    if units.get("length") not in LENGTH or units.get("angle") not in ANGLE:
        raise ModelFileError(f"{where}: 'units' must state length (m|mm) and angle (rad|deg), got {units!r}")
    L, A = LENGTH[units["length"]], ANGLE[units["angle"]]
    par = doc.get("parallel")
    if not isinstance(par, dict):
        raise ModelFileError(f"{where}: kind parallel needs a 'parallel:' mapping")
    typ = par.get("type")
    if typ not in TYPES:
        raise ModelFileError(f"{where}: parallel.type must be {' or '.join(TYPES)}, got {typ!r}")
    name = str(doc.get("name", "parallel"))
    desc = str(doc.get("description", ""))
    if typ == GOUGH_STEWART:
        known = {"type", "base_anchors", "platform_anchors", "legs", "home"}
        unknown = sorted(set(par) - known)
        if unknown:
            raise ModelFileError(f"{where}: parallel: unknown keys {unknown} for {typ}")
        base = _points(par.get("base_anchors"), 6, 3, f"{where}: parallel.base_anchors", L)
        plat = _points(par.get("platform_anchors"), 6, 3, f"{where}: parallel.platform_anchors", L)
        act = _actuators(par.get("legs"), 6, f"{where}: parallel.legs", L)
        h = _pose(par.get("home"), f"{where}: parallel.home", L, A, required=True)
        home = np.array([h.get(k, 0.0) for k in POSE_KEYS])
        tool = _pose(doc.get("tool"), f"{where}: tool", L, A, required=False)
        kw = {k: act[k] for k in ("max_velocity", "max_acceleration", "encoder") if k in act}
        m = gough_stewart(name, base, plat, act["limits"], home, tool=tool, offsets=act.get("offsets"),
                          description=desc, **kw)
        q = m.home_q
        bad = np.flatnonzero((q < m.lower) | (q > m.upper))
        if bad.size:
            k = int(bad[0])
            raise ModelFileError(f"{where}: parallel.home: leg {k + 1} is {q[k] / L:.6g} {units['length']} long "
                                 f"there, outside parallel.legs.limits [{m.lower[k] / L:.6g}, "
                                 f"{m.upper[k] / L:.6g}]")
        return m
    known = {"type", "pivots", "struts", "branch"}
    unknown = sorted(set(par) - known)
    if unknown:
        raise ModelFileError(f"{where}: parallel: unknown keys {unknown} for {typ}")
    if doc.get("tool"):
        raise ModelFileError(f"{where}: tool: a planar-struts robot has no tool frame (its pose is the hinge x, y)")
    piv = _points(par.get("pivots"), 2, 2, f"{where}: parallel.pivots", L)
    if np.linalg.norm(piv[1] - piv[0]) <= 0:
        raise ModelFileError(f"{where}: parallel.pivots: the two pivots coincide")
    act = _actuators(par.get("struts"), 2, f"{where}: parallel.struts", L)
    branch = par.get("branch", 1)
    if branch not in (1, -1):
        raise ModelFileError(f"{where}: parallel.branch: 1 (hinge left of pivot1 -> pivot2) or -1, got {branch!r}")
    kw = {k: act[k] for k in ("max_velocity", "max_acceleration", "encoder") if k in act}
    return planar_struts(name, piv, act["limits"], branch, offsets=act.get("offsets"), description=desc, **kw)


def parallel_to_dict(model: ParallelModel, length: str = "m", angle: str = "rad") -> dict:
    """Current parameter values (nominal or calibrated) in the stated units."""
    L, A = 1 / LENGTH[length], 1 / ANGLE[angle]
    g = model.geometry()

    def r(x: float) -> float:
        return float(round(float(x), 12))

    def pts(a):
        return [[r(x * L) for x in p] for p in a]

    lim = [[r(j.lower * L), r(j.upper * L)] for j in model.joints]
    j0 = model.joints[0]
    act: dict = {"limits": lim[0] if all(x == lim[0] for x in lim) else lim,
                 "offsets": [r(x * L) for x in g["offset"]],
                 "max_velocity": r(j0.max_velocity * L), "max_acceleration": r(j0.max_acceleration * L)}
    if j0.encoder:
        e = j0.encoder
        act["encoder"] = {"counts_per_m": r(e.counts_per_unit), "gear": r(e.gear), "direction": e.direction,
                          "zero": r(e.zero)}
    doc: dict = {"format": FORMAT, "name": model.name, "description": model.description, "kind": "parallel",
                 "units": {"length": length, "angle": angle}}
    if model.type == PLANAR_STRUTS:
        doc["parallel"] = {"type": PLANAR_STRUTS, "pivots": pts(g["pivots"]), "struts": act,
                           "branch": model.branch}
        return doc
    home = {k: r(v * (A if k.startswith("r") else L)) for k, v in zip(POSE_KEYS, model.home, strict=True)}
    doc["parallel"] = {"type": GOUGH_STEWART, "base_anchors": pts(g["base"]), "platform_anchors": pts(g["platform"]),
                       "legs": act, "home": home}
    doc["tool"] = {k: r(model.param(f"tcp.{k}") * (A if k.startswith("r") else L)) for k in POSE_KEYS}
    return doc
