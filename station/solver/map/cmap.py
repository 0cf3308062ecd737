"""The configuration-space correction map (docs/map.md, ``station-map/1``): build, look up, calibrated control,
measuring kinematics. Notation of the seed:

- PM: the sample set of configurations x (actuator values, SI) the robot was commanded to;
- GDK(x): the pose measured there (robot base frame); IK/DK: the model's inverse/direct kinematics;
- KSF_PM(x) = x - IK(GDK(x)): the correction summand at a sample;
- KSF_KR: KSF_PM extended to the whole configuration space (multilinear on the grid or barycentric on its
  Kuhn simplices, extrapolated beyond the sampled box; grid nodes the robot cannot assemble are filled
  with the smoothest continuation);
- calibrated control: to reach P command c with c - KSF_KR(c) = IK(P) (the seed's IK(P) + KSF_KR(IK(P)) is
  the first step of this fixed-point iteration);
- measuring kinematics: read x, report DK(x - KSF_KR(x)).

The model may be the nominal one or a parametric calibration of it (the map then holds what the
parameters leave: compliance, backlash, gear errors). Pure: arrays and dicts in, arrays and dicts out."""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from station.safeio import dumps_json
from station.solver.map.grid import MESHES, Grid
from station.solver.map.poses import (
    FULL,
    MapError,
    check_columns,
    is_parallel,
    output_columns,
    to_targets,
    to_vectors,
)

FORMAT = "station-map/1"
ABSURD = 1e6  # m or rad: a map value beyond this is a damaged file, not a robot
UNITS = ("SI: actuator values and summands in m (prismatic) or rad (revolute); positions in m; rotations as "
         "rotation vectors in rad; robot base frame")
SNAP_TOL = 0.05  # a sample may lie this fraction of the level spacing off its grid node (servo following error)
DOMAIN_MARGIN = 0.05  # lookups are served this fraction of the actuator range beyond the limits
MAX_SUMMAND = 0.1  # a summand above this fraction of the actuator range means a wrong frame or unit
IK_TOL = 1e-9  # m / rad: IK(GDK(x)) must reproduce the measured pose this well
FIXED_POINT_TOL = 1e-13
FIXED_POINT_ITER = 50


def working_model(nominal, calibration: dict | None):
    """The model the map sits on: the nominal one or its parametric calibration."""
    if not calibration:
        return nominal
    try:
        return nominal.with_params(calibration)
    except KeyError as e:
        raise MapError(f"calibration: {str(e).strip(chr(34) + chr(39))}") from None


def _unbounded(model):
    """``model`` without joint limits: IK(GDK(x)) may legitimately lie beyond them."""
    return model.with_joints(tuple(replace(j, lower=-np.inf, upper=np.inf) for j in model.joints))


def _ik_closed(model, targets: np.ndarray, message: str) -> np.ndarray:
    """A parallel robot's closed-form IK without limits; MapError ``message.format(row, reason)`` for the
    first pose it cannot reach."""
    q, ok, reasons = model.ik_closed(targets, check_limits=False)
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        raise MapError(message.format(i + 1, reasons[i]), i)
    return q


def second_configurations(model, x: np.ndarray, measured: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
    """x' = IK(GDK(x)) for every sample: closed form for parallel robots, Newton from x for serial ones (for a
    position-only measurement of a redundant arm: the nearby solution). MapError names the first sample whose
    measured pose the model cannot produce near x."""
    targets = to_targets(measured, cols)
    if is_parallel(model):
        return _ik_closed(model, targets, "sample {}: the measured pose {}")
    res = _unbounded(model).ik(targets, x, position_only=cols != FULL, tol_pos=1e-11, tol_rot=1e-11,
                               max_iter=100)
    bad = (res.position_error > IK_TOL) | (res.orientation_error > IK_TOL)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MapError(f"sample {i + 1}: no configuration near x reaches the measured pose (IK left "
                       f"{res.position_error[i]:.3g} m, {res.orientation_error[i]:.3g} rad): are the measurements "
                       f"in the robot base frame, in SI or with units in the header?", i)
    return res.q


def infer_levels(x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> list[np.ndarray]:
    """Grid levels from sample configurations: per actuator, values closer than 1e-3 of its range form one
    level (encoder readings scatter around the commanded level). A level holding less than a quarter of the
    average share of samples is a configuration off the grid, not a level: MapError names it."""
    out = []
    for i in range(x.shape[1]):
        order = np.argsort(x[:, i], kind="stable")
        v = x[order, i]
        tol = 1e-3 * max(float(upper[i] - lower[i]), 1e-12)
        cuts = np.flatnonzero(np.diff(v) > tol) + 1
        groups = np.split(np.arange(len(v)), cuts)
        share = len(v) / len(groups)
        for g in groups:
            if len(groups) > 1 and len(g) < 0.25 * share:
                row = int(order[g[0]])
                raise MapError(f"sample {row + 1}: configuration is not on the grid: x{i + 1} = {v[g[0]]:.9g} is a "
                               f"level of only {len(g)} sample(s), the others hold {share:.0f} on average", row)
        out.append(np.array([v[g].mean() for g in groups]))
    return out


def model_parameters(model) -> dict[str, float]:
    return {n: float(v) for n, v in zip(model.param_names, model.params, strict=True)}


@dataclass
class CorrectionMap:
    model: str
    kind: str  # "serial" | "parallel"
    actuators: tuple[str, ...]  # "prismatic" | "revolute" per actuator
    lower: np.ndarray  # actuator limits of the model (SI)
    upper: np.ndarray
    nominal: dict[str, float]  # the nominal parameters the map was built with
    calibration: dict | None  # {"source": str, "parameters": {name: SI}} or None
    pose: tuple[str, ...]  # measured pose components the summands came from
    mesh: str  # "grid" | "simplex"
    grid: Grid
    values: np.ndarray  # (M, n) summand at every grid node
    counts: np.ndarray  # (M,) samples per node; 0: filled (no measurement)
    domain_lower: np.ndarray
    domain_upper: np.ndarray
    samples_x: np.ndarray  # (S, n)
    samples_pose: np.ndarray  # (S, k)
    samples_summand: np.ndarray  # (S, n)
    statistics: dict = field(default_factory=dict)
    # the payload the model carried when the map was built ({"mass": kg, "com": [x, y, z] m}): the compliance
    # terms of a calibration under the map deflect the joints under that load only
    payload: dict | None = None

    @property
    def n(self) -> int:
        return len(self.actuators)

    # ---- the model the map belongs to ------------------------------------------------------------
    def model_for(self, nominal):
        """The working model (``nominal`` plus the map's parametric calibration) after checking that
        ``nominal`` is the model the map was built with."""
        if nominal.name != self.model:
            raise MapError(f"the map was built for model {self.model!r}, not {nominal.name!r}")
        if nominal.n_joints != self.n:
            raise MapError(f"the map has {self.n} actuators, model {nominal.name} has {nominal.n_joints}")
        # first: a load missing or different is what a user must be told, not the compliance names it implies
        from station.kinematics.gravity import payload_dict, same_payload, show_payload

        if not same_payload(self.payload, payload_dict(nominal)):
            raise MapError(f"the map was built with {show_payload(self.payload)} on the tool, model {nominal.name} "
                           f"carries {show_payload(payload_dict(nominal))}: give the same --payload")
        have = model_parameters(nominal)
        for name, v in self.nominal.items():
            if name not in have or not math.isclose(have[name], v, rel_tol=0, abs_tol=1e-12):
                got = "missing" if name not in have else f"{have[name]:.9g}"
                raise MapError(f"model {nominal.name} differs from the one the map was built with: {name} is {got}, "
                               f"the map has {v:.9g}")
        if np.any(np.abs(nominal.lower - self.lower) > 1e-12) or np.any(np.abs(nominal.upper - self.upper) > 1e-12):
            raise MapError(f"model {nominal.name} has other actuator limits than the one the map was built with")
        return working_model(nominal, (self.calibration or {}).get("parameters"))

    # ---- lookup -----------------------------------------------------------------------------------
    def outside(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, dtype=float))
        return np.any((x < self.domain_lower) | (x > self.domain_upper) | ~np.isfinite(x), axis=1)

    def _check_inside(self, x: np.ndarray, what: str, why: str = "") -> None:
        out = self.outside(x)
        if out.any():
            i = int(np.flatnonzero(out)[0])
            k = int(np.flatnonzero((x[i] < self.domain_lower) | (x[i] > self.domain_upper) | ~np.isfinite(x[i]))[0])
            raise MapError(f"{what} {i + 1}: {why}x{k + 1} = {x[i, k]:.9g} {self._unit(k)}{', which' if why else ''} "
                           f"is outside the map "
                           f"({self.domain_lower[k]:.9g} .. {self.domain_upper[k]:.9g} {self._unit(k)})", i)

    def _unit(self, k: int) -> str:
        return "rad" if self.actuators[k] == "revolute" else "m"

    def summand(self, x, what: str = "configuration") -> np.ndarray:
        """KSF_KR(x) ``(N, n)``; MapError for a configuration outside the map's domain."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[1] != self.n:
            raise MapError(f"the map has {self.n} actuators, got {x.shape[1]} values per configuration")
        self._check_inside(x, what)
        return self.grid.interpolate(self.values, x, self.mesh)

    # ---- calibrated control -------------------------------------------------------------------------
    def command(self, nominal, targets, cols: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated control: actuator commands ``c (N, n)`` that reach the target poses (pose vectors with
        columns ``cols``), and the nominal IK(P) ``(N, n)``. MapError names the first unreachable target."""
        model = self.model_for(nominal)
        cols = check_columns(model, tuple(cols), "targets")
        targets = np.atleast_2d(np.asarray(targets, dtype=float))
        x_p = self._ik(model, targets, cols)
        self._check_inside(x_p, "target", "unreachable: its inverse kinematics gives ")
        c = x_p + self.summand(x_p, "target")  # the seed's first-order command
        for _ in range(FIXED_POINT_ITER):
            inside = ~self.outside(c)
            c_new = c.copy()
            c_new[inside] = x_p[inside] + self.grid.interpolate(self.values, c[inside], self.mesh)
            step = np.max(np.abs(c_new - c)) if len(c) else 0.0
            c = c_new
            if step < FIXED_POINT_TOL:
                break
        lo, hi = nominal.lower, nominal.upper
        bad = np.any((c < lo - 1e-12) | (c > hi + 1e-12), axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            k = int(np.flatnonzero((c[i] < lo - 1e-12) | (c[i] > hi + 1e-12))[0])
            below = c[i, k] < lo[k]
            lim = lo[k] if below else hi[k]
            p = next((p for p in range(4, 10) if f"{c[i, k]:.{p}g}" != f"{lim:.{p}g}"), 10)  # digits that differ
            raise MapError(f"target {i + 1}: unreachable: x{k + 1} {c[i, k]:.{p}g} {self._unit(k)} "
                           f"{'below' if below else 'above'} {lim:.{p}g} {self._unit(k)} (the corrected command is "
                           "outside the actuator limits)", i)
        return c, x_p

    def _ik(self, model, targets: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
        T = to_targets(targets, cols)
        if is_parallel(model):
            return _ik_closed(model, T, "target {}: unreachable: {}")
        # serial: Newton from the sample configurations whose poses lie nearest to each target
        seeds_T = model.fk(self.samples_x).reshape(-1, 4, 4)
        pos = T[:, :3, 3] if T.ndim == 3 else T[:, :3]
        d = np.linalg.norm(pos[:, None, :] - seeds_T[None, :, :3, 3], axis=2)
        order = np.argsort(d, axis=1)[:, :6]
        free = _unbounded(model)
        q = np.full((len(T), self.n), np.nan)
        todo = np.arange(len(T))
        for k in range(order.shape[1]):
            if todo.size == 0:
                break
            res = free.ik(T[todo], self.samples_x[order[todo, k]], position_only=cols != FULL, tol_pos=1e-11,
                          tol_rot=1e-11, max_iter=150)
            good = (res.position_error < IK_TOL) & (res.orientation_error < IK_TOL) & ~self.outside(res.q)
            q[todo[good]] = res.q[good]
            todo = todo[~good]
        if todo.size:
            i = int(todo[0])
            raise MapError(f"target {i + 1}: unreachable: no configuration inside the map reaches it", i)
        return q

    # ---- measuring kinematics ------------------------------------------------------------------------
    def measure(self, nominal, x) -> tuple[np.ndarray, tuple[str, ...]]:
        """Measuring kinematics: the poses ``DK(x - KSF_KR(x))`` of actuator readings ``x (N, n)`` as pose
        vectors, and their columns."""
        model = self.model_for(nominal)
        x = np.atleast_2d(np.asarray(x, dtype=float))
        xc = x - self.summand(x, "reading")
        cols = output_columns(model)
        if is_parallel(model):
            res = model.fk_solve(xc)
            if not res.ok.all():
                i = int(np.flatnonzero(~res.ok)[0])
                raise MapError(f"reading {i + 1}: {res.reason[i]}", i)
            return to_vectors(res.T, cols), cols
        return to_vectors(model.fk(xc), cols), cols

    # ---- JSON ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        def rows(a):
            return [[float(v) for v in r] for r in np.atleast_2d(a)]

        return {
            "format": FORMAT,
            "units": UNITS,
            "model": {"name": self.model, "kind": self.kind, "actuators": list(self.actuators),
                      "lower": [float(v) for v in self.lower], "upper": [float(v) for v in self.upper],
                      "parameters": dict(self.nominal), "payload": self.payload},
            "calibration": self.calibration,
            "pose": list(self.pose),
            "mesh": {"type": self.mesh, "levels": [[float(v) for v in lv] for lv in self.grid.levels],
                     "shape": list(self.grid.shape), "order": "C",
                     "simplices": "kuhn" if self.mesh == "simplex" else None},
            "domain": {"lower": [float(v) for v in self.domain_lower], "upper": [float(v) for v in self.domain_upper]},
            "nodes": {"summand": rows(self.values), "samples": [int(c) for c in self.counts]},
            "samples": {"x": rows(self.samples_x), "pose": rows(self.samples_pose),
                        "summand": rows(self.samples_summand)},
            "statistics": dict(self.statistics),
        }

    def dumps(self) -> str:
        return dumps_json(self.to_dict(), indent=1) + "\n"  # strict JSON: a NaN statistic is null

    @classmethod
    def from_dict(cls, d, where: str = "<map>") -> CorrectionMap:
        r = _MapReader(where)
        if not isinstance(d, dict):
            raise MapError(f"{where}: not a JSON object")
        if d.get("format") != FORMAT:
            raise r.fail("format", f"{d.get('format')!r} is not {FORMAT!r}")
        try:
            m = d["model"]
            acts, lower, upper, nominal = r.model(m)
            n = len(acts)
            mesh = d["mesh"]
            grid = r.mesh(mesh, n)
            values, counts = r.nodes(d["nodes"], grid, n)
            pose = tuple(str(c) for c in d["pose"])
            sx, sp_, ss = r.samples(d["samples"], n, len(pose))
            dom = d["domain"]
            payload = r.payload(m.get("payload"))
            cal = d.get("calibration")
            if cal is not None and not (isinstance(cal, dict) and isinstance(cal.get("parameters"), dict)):
                raise r.fail("calibration", "expected null or {source, parameters: {name: value}}")
            return cls(str(m["name"]), str(m.get("kind", "serial")), acts, lower, upper, nominal, cal, pose,
                       mesh["type"], grid, values, counts, r.arr(dom["lower"], "domain.lower", (n,)),
                       r.arr(dom["upper"], "domain.upper", (n,)), sx, sp_, ss, dict(d.get("statistics") or {}),
                       payload)
        except KeyError as e:
            raise MapError(f"{where}: missing field {e.args[0]!r}") from None
        except (TypeError, AttributeError, ValueError, IndexError, OverflowError) as e:
            raise MapError(f"{where}: malformed map ({type(e).__name__}: {' '.join(str(e).split())[:200]})") from None


class _MapReader:
    """The parts of a map file as arrays, checked (finite, within any robot's range, of the stated shape);
    errors name the file and the field."""

    def __init__(self, where: str) -> None:
        self.where = where

    def fail(self, f: str, msg: str) -> MapError:
        return MapError(f"{self.where}: {f}: {msg}")

    def arr(self, v, f, shape=None):
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise self.fail(f, "expected numbers") from None
        if not np.all(np.isfinite(a)):
            raise self.fail(f, "not finite")
        if np.any(np.abs(a) > ABSURD):  # no actuator value, position or correction of a robot is this large
            raise self.fail(f, f"beyond any robot's range (|value| <= {ABSURD:g} m or rad)")
        if shape is not None and (a.ndim != len(shape) or any(s is not None and s != t
                                                              for s, t in zip(shape, a.shape, strict=True))):
            raise self.fail(f, f"expected shape {tuple('N' if s is None else s for s in shape)}, got {a.shape}")
        return a

    def model(self, m) -> tuple:
        """``(actuators, lower, upper, nominal parameters)`` of the map's model."""
        acts = tuple(str(a) for a in m["actuators"])
        n = len(acts)
        if n < 1 or any(a not in ("prismatic", "revolute") for a in acts):
            raise self.fail("model.actuators", "expected a list of prismatic|revolute")
        lower, upper = self.arr(m["lower"], "model.lower", (n,)), self.arr(m["upper"], "model.upper", (n,))
        return acts, lower, upper, {str(k): float(v) for k, v in dict(m["parameters"]).items()}

    def mesh(self, mesh, n: int) -> Grid:
        if mesh.get("type") not in MESHES:
            raise self.fail("mesh.type", f"expected {' or '.join(MESHES)}, got {mesh.get('type')!r}")
        if len(mesh["levels"]) != n:
            raise self.fail("mesh.levels", f"expected {n} lists of levels")
        try:
            return Grid.of([self.arr(lv, f"mesh.levels[{i}]", (None,)) for i, lv in enumerate(mesh["levels"])])
        except ValueError as e:
            raise self.fail("mesh.levels", str(e)) from None

    def nodes(self, nodes, grid: Grid, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The summand at every node and how many samples each rests on."""
        values = self.arr(nodes["summand"], "nodes.summand", (grid.size, n))
        raw = nodes["samples"]
        if not isinstance(raw, list) or len(raw) != grid.size or \
                any(type(c) is not int or not 0 <= c <= 10**9 for c in raw):
            raise self.fail("nodes.samples", f"expected {grid.size} sample counts (integers >= 0)")
        return values, np.asarray(raw, dtype=int)

    def samples(self, s, n: int, n_pose: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        sx = self.arr(s["x"], "samples.x", (None, n))
        return sx, self.arr(s["pose"], "samples.pose", (len(sx), n_pose)), \
            self.arr(s["summand"], "samples.summand", (len(sx), n))

    def payload(self, payload) -> dict | None:
        if payload is None:
            return None
        if not (isinstance(payload, dict) and set(payload) == {"mass", "com"}):
            raise self.fail("model.payload", "expected null or {mass: kg, com: [x, y, z] m}")
        mass = self.arr(payload["mass"], "model.payload.mass", ())
        if mass < 0:
            raise self.fail("model.payload.mass", "a mass is >= 0")
        return {"mass": float(mass), "com": [float(c) for c in self.arr(payload["com"], "model.payload.com", (3,))]}


def build_map(nominal, x, measured, pose, *, mesh: str = "grid", levels=None, calibration: dict | None = None,
              calibration_source: str | None = None) -> CorrectionMap:
    """KSF_PM at every sample and its extension KSF_KR.

    ``x (S, n)``: the sample configurations (as read back; they must sit on a grid within 5 % of its level
    spacing); ``measured (S, k)``: GDK(x) as pose vectors with columns ``pose`` (base frame, SI);
    ``levels``: the plan's grid levels (default: inferred from ``x``); ``calibration``: parameter values
    of a parametric calibration of ``nominal`` the map sits on. Several samples on one node are averaged."""
    t0 = time.perf_counter()
    if mesh not in MESHES:
        raise MapError(f"mesh must be one of {', '.join(MESHES)}, got {mesh!r}")
    x = np.atleast_2d(np.asarray(x, dtype=float))
    measured = np.atleast_2d(np.asarray(measured, dtype=float))
    if x.shape[1] != nominal.n_joints:
        raise MapError(f"model {nominal.name} has {nominal.n_joints} actuators, the samples have {x.shape[1]}")
    if len(x) != len(measured) or len(x) == 0:
        raise MapError("need one measured pose per sample configuration, at least one sample")
    model = working_model(nominal, calibration)
    cols = check_columns(model, tuple(pose), "samples")
    lo, hi = nominal.lower, nominal.upper
    grid = Grid.of(infer_levels(x, lo, hi) if levels is None else levels)
    if grid.n != nominal.n_joints:
        raise MapError(f"levels for {grid.n} actuators, the model has {nominal.n_joints}")
    node, rel = grid.nearest(x)
    off = np.max(rel, axis=1)
    if np.any(off > SNAP_TOL):
        i = int(np.argmax(off > SNAP_TOL))
        raise MapError(f"sample {i + 1}: configuration is not on the grid (off its nearest node by "
                       f"{off[i]:.0%} of the level spacing; allowed {SNAP_TOL:.0%})", i)
    xp = second_configurations(model, x, measured, cols)
    summand = x - xp
    span = np.maximum(hi - lo, 1e-12)
    big = np.abs(summand) > MAX_SUMMAND * span
    if big.any():
        i, k = (int(v[0]) for v in np.nonzero(big))
        unit = "rad" if model.joints[k].revolute else "m"
        raise MapError(f"sample {i + 1}: correction of x{k + 1} is {summand[i, k]:.6g} {unit}, more than "
                       f"{MAX_SUMMAND:.0%} of its range: are the measurements in the robot base frame and in the "
                       f"header's units?", i)
    counts = np.bincount(node, minlength=grid.size)
    values = np.zeros((grid.size, nominal.n_joints))
    np.add.at(values, node, summand)
    known = counts > 0
    values[known] /= counts[known, None]
    values = grid.fill(values, known)
    dom_lo = np.minimum(lo, grid.lower) - DOMAIN_MARGIN * span
    dom_hi = np.maximum(hi, grid.upper) + DOMAIN_MARGIN * span
    acts = tuple(j.kind for j in nominal.joints)
    cal = None
    if calibration:
        cal = {"source": calibration_source, "parameters": {k: float(v) for k, v in calibration.items()}}
    from station.kinematics.gravity import payload_dict

    cm = CorrectionMap(nominal.name, getattr(nominal, "kind", "serial"), acts, lo.copy(), hi.copy(),
                       model_parameters(nominal), cal, cols, mesh, grid, values, counts, dom_lo, dom_hi, x,
                       measured, summand, payload=payload_dict(nominal))
    resid = np.abs(cm.grid.interpolate(values, x, mesh) - summand)
    cm.statistics = {
        "n_samples": int(len(x)), "n_nodes": int(grid.size), "n_measured_nodes": int(known.sum()),
        "n_filled_nodes": int((~known).sum()), "max_off_grid": float(off.max()),
        "summand_max": [float(v) for v in np.max(np.abs(summand), axis=0)],
        "summand_rms": [float(v) for v in np.sqrt(np.mean(summand ** 2, axis=0))],
        "max_residual_at_samples": [float(v) for v in resid.max(axis=0)],
        "build_seconds": time.perf_counter() - t0,
        "id": hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()[:16],
    }
    return cm
