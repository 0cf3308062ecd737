"""The least-squares problem of a touch calibration: unknowns, residuals and the analytic Jacobian.

Unknown vector x = [selected model parameters, instrument frame (base.*), unknown reference points].
Residual of sample i (3 rows): ``r_i = p_tool(q_i; x) - c_i`` where ``c_i`` is the reference point touched
(known or unknown) or, with an instrument, the measured tip position in the instrument frame; in that case
the model's ``base.*`` frame is the instrument-to-robot-base transform, a nuisance unknown."""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from station.kinematics import se3
from station.kinematics.chain import RX, RY, RZ
from station.solver.folded import FoldedChain
from station.solver.observations import Observations, SolverInputError

_NONE = np.zeros(0, dtype=int)
COMPLIANCE_UNIT = "rad/(N m)"


def human_unit(unit: str) -> tuple[float, str]:
    """(factor, label) to show a value of SI ``unit`` to people: mm, deg, urad/(N m)."""
    if unit == "rad":
        return 180.0 / math.pi, "deg"
    if unit == COMPLIANCE_UNIT:
        return 1e6, "urad/(N m)"
    return 1e3, "mm"
BASE6 = ("base.x", "base.y", "base.z", "base.rz", "base.ry", "base.rx")


def angle_params(model) -> set[str]:
    """Names of parameters that are angles (their chain element is a rotation)."""
    ch = model.chain
    return {model.param_names[p] for p, ax in zip(ch.param, ch.axis, strict=True) if p >= 0 and ax in (RX, RY, RZ)}


def characteristic_length(model, ang: set[str] | None = None) -> float:
    """Sum of the model's translation parameters (link lengths, tool) without the base: an upper bound
    of the reach. Angles are scaled by it so that rank decisions compare metres with metres."""
    ang = angle_params(model) if ang is None else ang
    total = sum(abs(v) for n, v in zip(model.param_names, model.params, strict=True)
                if n not in ang and not n.startswith(("base.", "offset.")))
    return max(float(total), 0.1)


_COMPILED: OrderedDict = OrderedDict()
_COMPILED_LOCK = threading.Lock()
COMPILED_CACHE_SIZE = 16


def compiled(model, model_idx: np.ndarray) -> tuple[FoldedChain, set[str], float]:
    """(folded chain, angle parameter names, characteristic length) of ``model`` for the identified
    parameters ``model_idx``: pure functions of the (immutable) model and the selection, kept for the
    last few selections so that repeated solves (re-solves while touching, Monte-Carlo) compile once.
    An entry holds the model itself and a copy of its parameter values: a hit is always the same model."""
    key = (id(model), model_idx.tobytes())
    with _COMPILED_LOCK:  # solves may run in worker threads (engine, TUI)
        hit = _COMPILED.get(key)
        if hit is not None and hit[0] is model and np.array_equal(hit[1], model.params):
            _COMPILED.move_to_end(key)
            return hit[2]
    ang = angle_params(model)
    out = (FoldedChain(model.chain, model.params, model_idx), ang, characteristic_length(model, ang))
    with _COMPILED_LOCK:
        _COMPILED[key] = (model, model.params.copy(), out)
        while len(_COMPILED) > COMPILED_CACHE_SIZE:
            _COMPILED.popitem(last=False)
    return out


class Problem:
    def __init__(self, model, obs: Observations, model_names: list[str], reference,
                 instrument_frame: str = "unknown", distances=(), planes=()) -> None:
        self.model = model
        self.obs = obs
        instrument = obs.measured is not None
        self.instrument = instrument
        # "unknown": the instrument-to-base transform is solved as the nuisance frame base.*;
        # "base": the measurements are already in the robot base frame
        self.frame_unknown = instrument and instrument_frame == "unknown"
        names = list(model_names)
        if self.frame_unknown:
            names += [b for b in BASE6 if b not in names]
        self.model_names = names
        self.model_idx = np.array([model.index(n) for n in names], dtype=int)
        # the chain with everything not identified folded into constant blocks (compiled once per model
        # and parameter selection); with a gravity load it is evaluated at the deflected joint values
        self.folded, ang, L = _load_aware(model, self.model_idx, obs.q)
        self.kinds = ["instrument" if self.frame_unknown and n.startswith("base.") else "model" for n in names]
        self.units = [COMPLIANCE_UNIT if n.startswith("compliance.") else "rad" if n in ang else "m" for n in names]
        # reference points: one per label, or per label and fixture position (``LABEL@FIXTURE``); touches
        # of a plane label lie on one unknown plane (per fixture position) instead
        keys = obs.keys
        self.keys = keys
        plane_labels = [str(p) for p in planes]
        on_plane = self._plane_touches(obs, plane_labels, instrument)
        labels = list(dict.fromkeys(keys[~on_plane].tolist()))
        self.known, self.unknown_points = self._references(reference, labels, plane_labels)
        self.point_names = [f"point.{lb}.{a}" for lb in self.unknown_points for a in "xyz"]
        # a plane: normal n = unit(n0 + a t1 + b t2) about a nominal normal n0 (fitted to the nominal tip
        # positions, fixed for the solve), offset d (n . p = d, m)
        self.plane_names = [f"plane.{k}.{c}" for k in self.plane_keys for c in ("a", "b", "d")]
        self.names = self.model_names + self.point_names + self.plane_names
        self.kinds += ["point"] * len(self.point_names) + ["plane"] * len(self.plane_names)
        self.units += ["m"] * len(self.point_names) + ["rad", "rad", "m"] * len(self.plane_keys)
        self.n_model = len(self.model_names)
        self.n_points = len(self.point_names)
        self._slots(keys, on_plane)
        self.length = L
        self._plane_frames = self._nominal_planes() if self.plane_keys else []
        self.distances = self._distance_specs(distances)
        # compliance columns (tau times a joint column, m per rad/(N m)) keep scale 1: the rank decisions are
        # relative and the equilibration of the posterior treats them like any other column
        self.scale = np.array([L if u == "rad" else 1.0 for u in self.units])
        self._angle_cols = np.flatnonzero(self.scale != 1.0)
        # lengths of the machine and the points; a prismatic offset is a zero reading, not a length
        self._lengths = np.array([u == "m" and not n.startswith("offset.") for n, u in zip(self.names, self.units,
                                                                                           strict=True)])
        self.x_nominal = np.concatenate([model.params[self.model_idx], np.zeros(len(self.point_names)),
                                         np.array([v for _, _, _, d in self._plane_frames for v in (0.0, 0.0, d)])])

    def _plane_touches(self, obs: Observations, plane_labels: list[str], instrument: bool) -> np.ndarray:
        """Which touches are on a plane (their label is one of ``plane_labels``); sets ``on_plane`` and
        ``plane_keys`` (one plane per label and fixture position)."""
        if plane_labels and instrument:
            raise SolverInputError("planes: with instrument measurements the touches are not on a reference")
        for lb in plane_labels:
            if lb not in set(obs.point.tolist()):
                raise SolverInputError(f"plane {lb!r}: no touches labelled {lb!r} (points: {', '.join(obs.labels)})")
        on_plane = np.array([p in plane_labels for p in obs.point], dtype=bool)
        self.on_plane = on_plane
        self.plane_keys = list(dict.fromkeys(obs.keys[on_plane].tolist()))
        return on_plane

    def _references(self, reference, labels: list[str], plane_labels: list[str]) -> tuple[dict, list[str]]:
        """``(known points {label: xyz}, unknown point labels)``: none with an instrument (it measures the
        tip), all unknown for ``"unknown"``, else the given coordinates (one fixture position only)."""
        if self.instrument:
            return {}, []
        if isinstance(reference, str):
            if reference != "unknown":
                raise SolverInputError(f"reference must be 'unknown' or {{label: xyz}}, got {reference!r}")
            return {}, labels
        if len(self.obs.fixtures) > 1 and dict(reference):
            raise SolverInputError("known reference points with several fixture positions: each position has "
                                   "its own points; give them as unknown (with known distances)")
        known: dict[str, np.ndarray] = {}
        for k, v in dict(reference).items():
            xyz = np.asarray(v, dtype=float)
            if xyz.shape != (3,) or not np.isfinite(xyz).all():
                raise SolverInputError(f"reference point {k!r}: expected 3 finite coordinates (m), got {v!r}")
            if str(k) in plane_labels:
                raise SolverInputError(f"reference point {k!r} is declared a plane")
            known[str(k)] = xyz
        return known, [lb for lb in labels if lb not in known]

    def _slots(self, keys: np.ndarray, on_plane: np.ndarray) -> None:
        """Where each touch's unknowns sit: its point slot or plane slot, its residual rows, the fixed target
        (a known point or the instrument's measurement)."""
        # sample -> unknown point slot (or -1 for a known point or a plane touch)
        slot = {lb: i for i, lb in enumerate(self.unknown_points)}
        self.slot = np.array([-1 if pl else slot.get(lb, -1) for lb, pl in zip(keys, on_plane, strict=True)],
                             dtype=int)
        pslot = {k: i for i, k in enumerate(self.plane_keys)}
        self.pslot = np.array([pslot[k] if pl else -1 for k, pl in zip(keys, on_plane, strict=True)], dtype=int)
        # residual rows a touch contributes: 3 for a point, 1 (the distance along the normal) on a plane
        self.rows_per_touch = np.where(on_plane, 1, 3)
        # (row, column) of the -1 entries of the unknown points in the stacked Jacobian
        self._has_slot = self.slot >= 0
        self._all_unknown = bool(self._has_slot.all())
        rows = np.flatnonzero(self._has_slot)
        self._point_rows = None
        if len(rows):
            self._point_rows = ((3 * rows[:, None] + np.arange(3)).ravel(),
                                (self.n_model + 3 * self.slot[rows][:, None] + np.arange(3)).ravel())
        if self.instrument:
            self.target_fixed = self.obs.measured
        else:
            self.target_fixed = np.zeros((len(self.obs), 3))
            for lb, xyz in self.known.items():
                self.target_fixed[(keys == lb) & ~on_plane] = xyz

    @property
    def n_unknowns(self) -> int:
        return len(self.names)

    # ---- planes and known distances ---------------------------------------------------------------
    def _nominal_planes(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
        """(n0, t1, t2, d0) per plane: the least-squares plane of the nominal tip positions of its touches
        (normal = the direction of least spread); n0 is the linearisation point of the plane's normal."""
        P = self.folded.evaluate(self.obs.q, self.model.params, jacobian=False)[0]
        out = []
        for k, key in enumerate(self.plane_keys):
            pts = P[self.pslot == k]
            if len(pts) < 3:
                raise SolverInputError(f"plane {key!r}: {len(pts)} touch(es); a plane needs at least 3, well spread")
            c = pts.mean(axis=0)
            _, sv, Vt = np.linalg.svd(pts - c)
            if len(sv) < 2 or sv[1] <= 1e-6 * max(sv[0], 1e-12):
                raise SolverInputError(f"plane {key!r}: its touches lie on a line; touch points spread over the plane")
            n0 = Vt[2] * (1.0 if Vt[2][np.argmax(np.abs(Vt[2]))] > 0 else -1.0)
            t1 = Vt[0] - n0 * (n0 @ Vt[0])
            t1 /= np.linalg.norm(t1)
            t2 = np.cross(n0, t1)
            out.append((n0, t1, t2, float(n0 @ c)))
        return out

    def plane_of(self, x: np.ndarray, k: int) -> tuple[np.ndarray, float]:
        """(unit normal, offset d) of plane ``k`` at ``x``: its points p satisfy n . p = d."""
        n0, t1, t2, _ = self._plane_frames[k]
        a, b, d = x[self._plane_col(k): self._plane_col(k) + 3]
        m = n0 + a * t1 + b * t2
        return m / np.linalg.norm(m), float(d)

    def _plane_col(self, k: int) -> int:
        return self.n_model + self.n_points + 3 * k

    def _apply_planes(self, x: np.ndarray, P: np.ndarray, r3: np.ndarray, J: np.ndarray | None = None) -> None:
        """Plane touches (in place): residual ``e n`` with ``e = n . p - d`` its distance from the plane (a
        3-vector of rank one: the tangential position on a plane is free); Jacobian ``n n^T dp/dx`` for
        the model and d/d(a, b, d) for the plane."""
        for k in range(len(self.plane_keys)):
            rows = np.flatnonzero(self.pslot == k)
            n0, t1, t2, _ = self._plane_frames[k]
            a, b, d = x[self._plane_col(k): self._plane_col(k) + 3]
            m = n0 + a * t1 + b * t2
            nm = float(np.linalg.norm(m))
            n = m / nm
            e = P[rows] @ n - d
            r3[rows] = e[:, None] * n
            if J is None:
                continue
            Jv = J.reshape(len(P), 3, -1)  # a view
            Jm = Jv[rows, :, : self.n_model]
            Jv[rows, :, : self.n_model] = n[None, :, None] * np.einsum("i,nik->nk", n, Jm)[:, None, :]
            c = self._plane_col(k)
            for j, t in enumerate((t1, t2)):
                dn = (t - n * (n @ t)) / nm
                Jv[rows, :, c + j] = (P[rows] @ dn)[:, None] * n + e[:, None] * dn
            Jv[rows, :, c + 2] = -n

    def plane_residuals(self, x: np.ndarray, P: np.ndarray | None = None) -> list[np.ndarray]:
        """Signed distance (m) of each plane's touches from the plane at ``x``."""
        if P is None:
            P = self.folded.evaluate(self.obs.q, self.full_params(x), jacobian=False)[0]
        out = []
        for k in range(len(self.plane_keys)):
            n, d = self.plane_of(x, k)
            out.append(P[self.pslot == k] @ n - d)
        return out

    def _distance_specs(self, distances) -> list[dict]:
        """Known distances ``[(a, b, metres, std metres)]`` -> one constraint per fixture position where
        both points were touched (each position has its own points; the distance is the same)."""
        out = []
        if not distances:
            return out
        if self.instrument:
            raise SolverInputError("distances: with instrument measurements the touches are not on reference points")
        fixtures = self.obs.fixtures if len(self.obs.fixtures) > 1 else [None]
        planes = set(self.obs.point[self.on_plane].tolist())
        for spec in distances:
            a, b, value, std = spec
            a, b = str(a), str(b)
            if a == b:
                raise SolverInputError(f"distance {a},{b}: the two points must differ")
            if not (math.isfinite(value) and value > 0) or not (math.isfinite(std) and std > 0):
                raise SolverInputError(f"distance {a},{b}: value and uncertainty must be positive finite lengths (m)")
            for lb in (a, b):
                if lb in planes:
                    raise SolverInputError(f"distance {a},{b}: {lb!r} is a plane, not a point")
                if lb not in set(self.obs.point.tolist()) and lb not in self.known:
                    raise SolverInputError(f"distance {a},{b}: no touches of point {lb!r} "
                                           f"(points: {', '.join(self.obs.labels)})")
            n0 = len(out)
            for f in fixtures:
                ka, kb = (lb if f is None else f"{lb}@{f}" for lb in (a, b))
                have = set(self.unknown_points) | set(self.known)
                if ka in have and kb in have:
                    out.append({"a": a, "b": b, "key_a": ka, "key_b": kb, "fixture": f, "value": float(value),
                                "std": float(std)})
            if len(out) == n0:
                raise SolverInputError(f"distance {a},{b}: no fixture position has touches of both points")
        return out

    def _point_col(self, key: str) -> int:
        """First column of unknown point ``key``, -1 for a known point."""
        return self.n_model + 3 * self.unknown_points.index(key) if key in self.unknown_points else -1

    def constraint_rows(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Known distances as weighted pseudo-observations: (g, G, s) with ``g_k = |p_a - p_b| - D_k`` (m),
        ``G = dg/dx`` (K, n_unknowns) and ``s`` the stated uncertainty (m): the estimator adds
        ``sum (g_k / s_k)^2`` (in units of the touch variance) to the cost, like a prior on a function of x."""
        K = len(self.distances)
        g, G, s = np.zeros(K), np.zeros((K, self.n_unknowns)), np.zeros(K)
        pts = self.points_of(x)
        for k, c in enumerate(self.distances):
            v = np.asarray(pts[c["key_a"]]) - np.asarray(pts[c["key_b"]])
            dist = float(np.linalg.norm(v))
            u = v / max(dist, 1e-300)
            g[k], s[k] = dist - c["value"], c["std"]
            ca, cb = self._point_col(c["key_a"]), self._point_col(c["key_b"])
            if ca >= 0:
                G[k, ca: ca + 3] += u
            if cb >= 0:
                G[k, cb: cb + 3] -= u
        return g, G, s

    def full_params(self, x: np.ndarray) -> np.ndarray:
        p = self.model.params.copy()
        p[self.model_idx] = x[: self.n_model]
        return p

    def points_of(self, x: np.ndarray) -> dict[str, np.ndarray]:
        pts = dict(self.known)
        for i, lb in enumerate(self.unknown_points):
            pts[lb] = x[self.n_model + 3 * i: self.n_model + 3 * i + 3]
        return pts

    def initial(self) -> np.ndarray:
        """Nominal model; unknown points at the mean nominal tip position of their touches; instrument
        frame by rigid registration (Kabsch) of nominal tip positions onto the measurements."""
        x = self.x_nominal.copy()
        P = self.folded.evaluate(self.obs.q, self.model.params, jacobian=False)[0]
        if self.frame_unknown:
            T0 = np.eye(4)
            T0[:3, :3], T0[:3, 3] = _kabsch(P, self.obs.measured)
            bi = [self.model.index(b) for b in BASE6]
            Tb = T0 @ _base_matrix(self.model.params[bi])
            rx, ry, rz = _matrix_to_rpy(Tb[:3, :3])
            vals = dict(zip(BASE6, [*Tb[:3, 3], rz, ry, rx], strict=True))
            for i, n in enumerate(self.model_names):
                if n in vals:
                    x[i] = vals[n]
        self._point_means(x, P)
        return x

    def _point_means(self, x: np.ndarray, P: np.ndarray) -> None:
        """Unknown points at the mean tip position of their touches (in place)."""
        n = len(self.unknown_points)
        if n == 1:
            x[self.n_model: self.n_model + 3] = P.mean(axis=0) if self._all_unknown else P[self._has_slot].mean(axis=0)
        elif n:
            sums = np.zeros((n, 3))
            np.add.at(sums, self.slot[self._has_slot], P[self._has_slot])
            x[self.n_model: self.n_model + self.n_points] = (
                sums / np.bincount(self.slot[self._has_slot], minlength=n)[:, None]).ravel()

    def initial_with_jacobian(self, scaled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``initial()`` with the residual and Jacobian there. Without an instrument frame one chain pass
        serves both: the model is at nominal and the Jacobian does not depend on the point values."""
        if self.frame_unknown or self.plane_keys:
            x = self.initial()
            return (x, *self.residual_jacobian(x, scaled))
        x = self.x_nominal.copy()
        r, J = self.residual_jacobian(x, scaled)  # points at 0: rows of unknown points are the tip positions
        P = r.reshape(-1, 3) + self.target_fixed * (self.slot < 0)[:, None]
        self._point_means(x, P)
        return x, (P - self._targets(x)).ravel(), J

    def residual(self, x: np.ndarray, fused: bool = True) -> np.ndarray:
        """Stacked residual (3N,). ``fused=False`` evaluates it through the kinematics layer's public
        ``Model.position`` instead of the solver's fused chain pass (same numbers; used as the baseline in
        bench/solver.py)."""
        if fused:
            P = self.folded.evaluate(self.obs.q, self.full_params(x), jacobian=False)[0]
        else:
            P = self.model.position(self.obs.q, self.full_params(x))
        return self._residual3(x, P).ravel()

    def _residual3(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        r3 = P - self._targets(x)
        if self.plane_keys:
            self._apply_planes(x, P, r3)
        return r3

    def residual_jacobian(self, x: np.ndarray, scaled: bool = False, q: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Residual (3N,) and Jacobian (3N, n_unknowns); ``scaled``: columns times ``self.scale`` (angles
        times the characteristic length). ``q``: other joint readings for the same touches (the
        identifiability analysis evaluates the Jacobian where the touches are exactly consistent)."""
        N = len(self.obs)
        J = np.zeros((3 * N, self.n_unknowns))
        Jm = J[:, : self.n_model]
        Jm.shape = (N, 3, self.n_model)  # a view (raises rather than copy): evaluate writes into J
        P, _ = self.folded.evaluate(self.obs.q if q is None else q, self.full_params(x), out=Jm)
        r3 = P - self._targets(x)
        if self._point_rows is not None:
            J[self._point_rows] = -1.0
        if self.plane_keys:
            self._apply_planes(x, P, r3, J)
        r = r3.ravel()
        if scaled and len(self._angle_cols):
            J[:, self._angle_cols] *= self.length
        return r, J

    def _joint_chain(self):
        """The folded chain with every joint's offset as a column (plus the identified parameters, which
        may differ from the model's values): d tip / d offset_k == d tip / d q_k."""
        offs = [self.model.index(f"offset.j{i + 1}") for i in range(self.model.n_joints)]
        idx = np.array(list(self.model_idx) + [o for o in offs if o not in set(self.model_idx.tolist())], dtype=int)
        cols = [int(np.flatnonzero(idx == o)[0]) for o in offs]
        return _load_aware(self.model, idx, self.obs.q)[0], cols

    def _tip_and_joint_jacobian(self, fold, cols, q: np.ndarray, params: np.ndarray):
        """Tip positions and d tip / d q at readings ``q``: with a gravity load the joints turn to
        ``q + C tau(q)``, so d tip / d q = J_theta (I + C d tau / d q)."""
        P, J = fold.evaluate(q, params)
        Jq = J[:, :, cols]
        js, ps = self.model.compliance_index
        if self.model.load is not None and len(js) and params[ps].any():
            dtau = self.model.gravity_torque(q, derivative=True)[1]
            D = np.zeros((self.model.n_joints, self.model.n_joints))
            D[js, js] = params[ps]
            Jq = Jq + np.einsum("nri,ij,njk->nrk", Jq, D, dtau)
        return P, Jq

    def joint_jacobian(self, x: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
        """d tip / d q ``(N, 3, n)`` at the touches' joint readings (or ``q``), the deflection included."""
        fold, cols = self._joint_chain()
        return self._tip_and_joint_jacobian(fold, cols, self.obs.q if q is None else q, self.full_params(x))[1]

    def consistent_q(self, x: np.ndarray, steps: int = 2) -> np.ndarray:
        """Joint readings near the recorded ones at which every touch is exactly on its target with the
        parameters ``x`` (Newton steps ``dq = -Jq^+ r_i`` per touch; residuals are small against the reach,
        so two steps leave ~|r|^3/L^2). Exact dependencies such as "a rotation about joint 1 moves the
        unknown point" hold only for consistent touches; measured ones break them by the noise."""
        fold, cols = self._joint_chain()
        params = self.full_params(x)
        tgt = self._targets(x)
        q = self.obs.q.copy()
        for _ in range(steps):
            P, Jq = self._tip_and_joint_jacobian(fold, cols, q, params)
            # minimum-norm dq = Jq^T (Jq Jq^T)^-1 r (damped by 1e-12 of the trace: a robot whose tip cannot
            # move in some direction keeps that part of the residual)
            A = Jq @ Jq.transpose(0, 2, 1)
            tr = np.trace(A, axis1=1, axis2=2)
            # a tip on every joint's axis (a rotor's own link) cannot move at all: nothing to move there
            A += np.where(tr > 0, 1e-12 * tr, 1.0)[:, None, None] * np.eye(3)
            r3 = P - tgt
            if self.plane_keys:
                self._apply_planes(x, P, r3)
            y = np.linalg.solve(A, r3[:, :, None])
            q -= (Jq.transpose(0, 2, 1) @ y)[:, :, 0]
        return q

    def first_joint_offset_column(self) -> int:
        """Column of the first joint's offset among the unknowns when ``shift_first_joint`` applies to it
        (identified, no identified element before that joint), else -1."""
        pj = self.folded.first_joint_param
        if self.plane_keys:  # a plane touch's residual is a projection: not moved rigidly with the tool
            return -1
        hit = np.flatnonzero(self.model_idx == pj) if pj >= 0 else []
        if not len(hit) or not self.folded.first_joint_shiftable:
            return -1
        return int(hit[0])

    def shift_first_joint(self, x: np.ndarray, r: np.ndarray, J: np.ndarray, delta: float, col: int | None = None):
        """``residual_jacobian`` at ``x`` with the first joint's offset changed by ``delta`` from the values
        ``r, J`` at ``x`` (scaled or not), without a chain pass: every tool position and every model
        column (all at or after that joint) moves by the same rigid motion ``T``; point columns do not
        change. Exact (to rounding); ``tests/solver/test_solver_folded.py`` compares it with a fresh pass."""
        T = self.folded.first_joint_motion(delta)
        N = len(self.obs)
        R, t = T[:3, :3], T[:3, 3]
        P = r.reshape(N, 3) + self._targets(x)
        x2 = x.copy()
        x2[self.first_joint_offset_column() if col is None else col] += delta
        r2 = (P @ R.T + t - self._targets(x2)).ravel()
        J2 = J.copy()
        src, dst = J[:, : self.n_model], J2[:, : self.n_model]
        src.shape = dst.shape = (N, 3, self.n_model)  # views
        np.matmul(R, src, out=dst)
        return r2, J2

    def _targets(self, x: np.ndarray) -> np.ndarray:
        if self.instrument or not self.unknown_points:
            return self.target_fixed
        if self._all_unknown:
            return x[self.n_model: self.n_model + self.n_points].reshape(-1, 3)[self.slot]
        tgt = self.target_fixed.copy()
        has = self._has_slot
        tgt[has] = x[self.n_model: self.n_model + self.n_points].reshape(-1, 3)[self.slot[has]]
        return tgt

    def tool_per_unit(self) -> np.ndarray:
        """Metres of tool motion per unit of each unknown: the characteristic length for angles, that
        times the rms gravity torque of the joint for a compliance (rad/(N m) x N m = rad), 1 for lengths."""
        out = np.where(np.array(self.units) == "rad", self.length, 1.0)
        for i, n in enumerate(self.names):
            if n.startswith("compliance."):
                j = int(n.split(".j")[1]) - 1
                tau = self.model.gravity_torque(self.obs.q)[:, j]
                out[i] = self.length * max(float(np.sqrt(np.mean(tau**2))), 1e-9)
        return out

    def scale_direction(self, x: np.ndarray) -> np.ndarray:
        """d x / d s for a uniform scaling of every length (model lengths and points) by (1 + s)."""
        return np.where(self._lengths, x, 0.0)


class CompliantChain:
    """A folded chain evaluated at the joint values deflected by gravity, ``theta = q + C tau(q)``
    (``Model.fk``), with the column of ``compliance.jN`` = ``tau_N(q)`` x the column of joint N's offset
    (``Model.jacobians``). ``inner`` is folded over the rigid parameters of the selection plus the offsets
    that the compliance columns need (``aux``, after the ``k`` selected columns)."""

    def __init__(self, model, inner: FoldedChain, k: int, comp_cols, q0: np.ndarray) -> None:
        self.model, self.inner, self.k, self.comp_cols = model, inner, k, comp_cols
        self.js, self.ps = model.compliance_index
        self.first_joint_param = inner.first_joint_param
        # shifting the first joint moves every column rigidly only if the torques do not change with it
        self.first_joint_shiftable = False
        self.first_joint_motion = inner.first_joint_motion
        self._q0, self._tau0 = q0, None

    def _tau(self, q: np.ndarray) -> np.ndarray:
        if q is self._q0:
            if self._tau0 is None:
                self._tau0 = self.model.gravity_torque(q)
            return self._tau0
        return self.model.gravity_torque(q)

    def evaluate(self, q, params, jacobian: bool = True, out=None):
        q = np.atleast_2d(q)
        tau = self._tau(q)
        theta = q.copy()
        theta[:, self.js] += params[self.ps] * tau[:, self.js]
        P, Jf = self.inner.evaluate(theta, params, jacobian)
        if not jacobian:
            return P, None
        J = out if out is not None else np.empty(Jf.shape[:2] + (self.k,))
        J[...] = Jf[:, :, : self.k]
        for col, j, aux in self.comp_cols:
            J[:, :, col] = tau[:, None, j] * Jf[:, :, aux]
        return P, J


def _load_aware(model, model_idx: np.ndarray, q0: np.ndarray):
    """``compiled`` for a model without a gravity load; with one, the ``CompliantChain`` around it."""
    if getattr(model, "load", None) is None or not len(model.compliance_index[0]):
        return compiled(model, model_idx)
    comp_p = set(model.compliance_index[1].tolist())
    rigid = [int(i) for i in model_idx if int(i) not in comp_p]
    idx = list(rigid)
    cols = []
    for col, p in enumerate(model_idx.tolist()):
        if p in comp_p:
            j = int(model.param_names[p].split(".j")[1]) - 1
            off = model.index(f"offset.j{j + 1}")
            if off not in idx:
                idx.append(off)
            cols.append((col, j, None, off))
    inner, ang, L = compiled(model, np.array(idx, dtype=int))
    # inner columns: rigid ones in order, then the extra offsets; map back to the selection's columns
    pos = {p: i for i, p in enumerate(idx)}
    k = len(model_idx)
    fold = _Reordered(inner, [pos[int(p)] if int(p) not in comp_p else -1 for p in model_idx], len(idx))
    comp_cols = [(col, j, k + pos[off]) for col, j, _, off in cols]
    return CompliantChain(model, fold, k, comp_cols, q0), ang, L


class _Reordered:
    """The inner chain's Jacobian with the selection's column order (compliance columns left as zeros,
    filled by ``CompliantChain``), followed by every inner column (``aux`` indices refer past ``k``)."""

    def __init__(self, inner: FoldedChain, order: list[int], n_inner: int) -> None:
        self.inner, self.order, self.n_inner = inner, order, n_inner
        self.first_joint_param = inner.first_joint_param
        self.first_joint_motion = inner.first_joint_motion

    def evaluate(self, q, params, jacobian: bool = True):
        P, Ji = self.inner.evaluate(q, params, jacobian)
        if not jacobian:
            return P, None
        k = len(self.order)
        J = np.zeros(Ji.shape[:2] + (k + self.n_inner,))
        for c, i in enumerate(self.order):
            if i >= 0:
                J[:, :, c] = Ji[:, :, i]
        J[:, :, k:] = Ji
        return P, J


def position_jacobian(chain, q: np.ndarray, params: np.ndarray, param_idx: np.ndarray, want: dict | None = None):
    """Tool positions ``(N, 3)`` and ``d position / d params[param_idx]`` ``(N, 3, k)``.

    The same chain semantics as ``station.kinematics.chain.forward`` (``T <- T E_k``, each element a
    translation along or rotation about a local axis), but only position rows and only the requested
    parameters, in a (3, ., N) memory layout, with runs of pose-independent elements multiplied once as
    4x4 matrices: the identification Jacobian costs about one forward kinematics evaluation.
    ``tests/solver/test_solver_problem.py`` checks it against ``Model.jacobians`` and finite differences."""
    q = np.atleast_2d(q)
    N, K = q.shape[0], chain.n_elements
    if want is None:
        want = element_columns(chain, param_idx)
    v = chain.values(q, params)  # (N, K)
    R = np.zeros((3, 3, N))  # R[:, c] = column c of the rotation (world axis c of the current frame)
    R[0, 0] = R[1, 1] = R[2, 2] = 1.0
    p = np.zeros((3, N))
    moving = chain.joint >= 0
    J = np.zeros((N, 3, len(param_idx)))
    C = None  # pending product of pose-independent elements
    pending: list[tuple[int, np.ndarray, np.ndarray]] = []  # rotation columns: w x (tool - o) at the end
    for k in range(K):
        ax = int(chain.axis[k])
        if C is not None and (moving[k] or k in want):
            p = p + np.einsum("abn,b->an", R, C[:3, 3])
            R = np.einsum("abn,bc->acn", R, C[:3, :3])
            C = None
        if k in want:  # R and p are replaced, never modified in place, so views stay valid
            if ax >= 3:
                pending.append((want[k], R[:, ax - 3], p))
            else:
                J[:, :, want[k]] = R[:, ax].T
        if not moving[k]:
            val = v[0, k]
            if val != 0.0:
                E = _elementary(ax, val)
                C = E if C is None else C @ E
            continue
        vk = v[:, k]
        if ax < 3:
            p = p + vk * R[:, ax]
        else:
            i, j = {RX: (1, 2), RY: (2, 0), RZ: (0, 1)}[ax]
            c, s = np.cos(vk), np.sin(vk)
            R = R.copy()
            ci = R[:, i].copy()
            R[:, i] = c * ci + s * R[:, j]
            R[:, j] = -s * ci + c * R[:, j]
    if C is not None:
        p = p + np.einsum("abn,b->an", R, C[:3, 3])
    for col, w, o in pending:
        d = p - o
        J[:, 0, col] = w[1] * d[2] - w[2] * d[1]
        J[:, 1, col] = w[2] * d[0] - w[0] * d[2]
        J[:, 2, col] = w[0] * d[1] - w[1] * d[0]
    return p.T.copy(), J


_EYE4 = np.eye(4)


def _elementary(ax: int, val: float) -> np.ndarray:
    E = _EYE4.copy()
    if ax < 3:
        E[ax, 3] = val
        return E
    i, j = {RX: (1, 2), RY: (2, 0), RZ: (0, 1)}[ax]
    c, s = math.cos(val), math.sin(val)
    E[i, i], E[i, j], E[j, i], E[j, j] = c, -s, s, c
    return E


def element_columns(chain, param_idx) -> dict[int, int]:
    """Chain element -> Jacobian column for the parameters ``param_idx``."""
    elem_of = {int(pi): k for k, pi in enumerate(chain.param) if pi >= 0}
    return {elem_of[int(i)]: col for col, i in enumerate(param_idx)}


def _base_matrix(vals) -> np.ndarray:
    """The base frame ``Tx Ty Tz Rz Ry Rx`` as one matrix (``se3.rpy_to_matrix`` convention, written out:
    this runs once per solve and scipy's Rotation costs more than the rest of the setup)."""
    x, y, z, rz, ry, rx = (float(v) for v in vals)
    cz, sz, cy, sy, cx, sx = math.cos(rz), math.sin(rz), math.cos(ry), math.sin(ry), math.cos(rx), math.sin(rx)
    return np.array([[cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx, x],
                     [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx, y],
                     [-sy, cy * sx, cy * cx, z],
                     [0.0, 0.0, 0.0, 1.0]])


def _matrix_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of the rotation part of ``_base_matrix``: (rx, ry, rz); near gimbal lock via scipy."""
    if abs(R[2, 0]) > 1.0 - 1e-9:
        return tuple(float(v) for v in se3.matrix_to_rpy(R))
    return math.atan2(R[2, 1], R[2, 2]), -math.asin(R[2, 0]), math.atan2(R[1, 0], R[0, 0])


def _kabsch(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum |R p + t - q|^2."""
    pc, qc = P.mean(axis=0), Q.mean(axis=0)
    H = (P - pc).T @ (Q - qc)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, qc - R @ pc
