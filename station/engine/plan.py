"""Pose plans: which joint positions touch which reference point, in which order.

Generated from a reference point's approximate location and the nominal model: inverse kinematics over a
spread of tool orientations inside a cone around the approach direction (6-DOF arms) or from a spread of joint
seeds (4-DOF arms, position only), kept inside joint limits with a margin; from the feasible candidates a greedy
D-optimal choice on the identification Jacobian (the parameters to identify plus the unknown point positions)
picks enough poses for the unknowns, the next best become held-out poses, and a nearest-neighbour tour with
2-opt orders them for short motion. Or listed in the procedure (``plan_from_joints``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from station.engine.cell import RefPoint
from station.kinematics import Model
from station.robot.errors import ConfigError


class PlanError(ConfigError):
    """No plan can be made as asked (unreachable point, too few feasible poses)."""


@dataclass
class PlannedPose:
    index: int
    point: str
    q: list[float]  # joint target that puts the nominal tool tip on the nominal point (SI)
    approach_q: list[float]  # same orientation, backed off along the approach direction
    set: str = "fit"  # "fit" | "holdout"

    @property
    def q_arr(self) -> np.ndarray:
        return np.asarray(self.q, float)

    @property
    def approach_arr(self) -> np.ndarray:
        return np.asarray(self.approach_q, float)


@dataclass
class PosePlan:
    poses: list[PlannedPose]
    settings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.poses)

    def to_dict(self) -> dict:
        return {"poses": [asdict(p) for p in self.poses], "settings": self.settings}

    @classmethod
    def from_dict(cls, d: dict) -> PosePlan:
        return cls([PlannedPose(**p) for p in d["poses"]], dict(d.get("settings", {})))

    def of_set(self, name: str) -> list[PlannedPose]:
        return [p for p in self.poses if p.set == name]


def _frame_with_z(z: np.ndarray, roll: float) -> np.ndarray:
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - z * (helper @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def _cone_dirs(axis: np.ndarray, cone: float, n: int, rng) -> np.ndarray:
    """``n`` unit vectors inside a cone of half-angle ``cone`` around ``axis`` (area-uniform)."""
    tilt = np.arccos(1 - rng.random(n) * (1 - np.cos(cone)))
    az = rng.random(n) * 2 * np.pi
    R = _frame_with_z(axis, 0.0)
    local = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    return local @ R.T


def _seeds(model: Model, q_start: np.ndarray, n: int, rng) -> np.ndarray:
    lo = np.maximum(model.lower, -np.pi)
    hi = np.minimum(model.upper, np.pi)
    out = lo + (hi - lo) * rng.random((n, model.n_joints))
    out[0] = np.clip(q_start, model.lower, model.upper)
    # half the seeds near the start pose: arms reach the cell mostly in the configuration they stand in
    k = n // 2
    out[1:k] = np.clip(q_start + rng.normal(0, 0.6, (k - 1, model.n_joints)), lo, hi)
    return out


def _candidates(model: Model, point: RefPoint, q_start, n, cone, clearance, roll, margin, rng):
    """Feasible (touch q, approach q) pairs for one point."""
    full = model.n_joints >= 6
    p = point.position
    back = p + point.approach * clearance
    if full:
        dirs = _cone_dirs(-point.approach, cone, n, rng)
        rolls = rng.uniform(-roll, roll, n)
        T = np.repeat(np.eye(4)[None], n, axis=0)
        for i in range(n):
            T[i, :3, :3] = _frame_with_z(dirs[i], rolls[i])
        T[:, :3, 3] = p
        # seeds: the start pose and perturbations of it, tried in turn for targets that have not converged
        best = None
        for s in _seeds(model, q_start, 6, rng):
            res = model.ik(T, s, max_iter=120)
            if best is None:
                best_q, best_ok = res.q.copy(), res.ok.copy()
                best = True
            else:
                take = ~best_ok & res.ok
                best_q[take] = res.q[take]
                best_ok |= res.ok
            if best_ok.all():
                break
        q_touch, ok = best_q, best_ok
        Ta = T.copy()
        Ta[:, :3, 3] = back
        ra = model.ik(Ta, q_touch, max_iter=80)
    else:
        seeds = _seeds(model, q_start, n, rng)
        res = model.ik(np.repeat(p[None], n, axis=0), seeds, position_only=True, max_iter=150)
        q_touch, ok = res.q, res.ok
        ra = model.ik(np.repeat(back[None], n, axis=0), q_touch, position_only=True, max_iter=80)
        if ok.any():  # keep the tool pointing into the cone: the axis of the tool frame best aligned inward
            R = model.fk(q_touch)[:, :3, :3]
            align = np.einsum("nij,i->nj", R, -point.approach)  # cos between each tool axis and the inward dir
            axis = np.argmax(np.abs(np.median(align[ok], axis=0)))
            sign = np.sign(np.median(align[ok, axis]))
            ok &= sign * align[:, axis] >= np.cos(cone)
    ok &= ra.ok & _inside(model, q_touch, margin) & _inside(model, ra.q, margin)
    ok &= np.max(np.abs(ra.q - q_touch), axis=1) < 0.6  # no configuration flip between approach and touch
    return q_touch[ok], ra.q[ok]


def _inside(model: Model, q: np.ndarray, margin_rad: float) -> np.ndarray:
    # the margin keeps room for the seating/compliance motion; prismatic joints get 5 mm
    m = np.array([margin_rad if j.revolute else 0.005 for j in model.joints])
    return np.all((q >= model.lower + m) & (q <= model.upper - m), axis=1)


def _info_rows(model: Model, q: np.ndarray, names: list[str], point_col: int, n_points: int) -> np.ndarray:
    """Identification Jacobian rows (N,3,P+3*n_points): model parameters, then -I for the touched point."""
    J = model.jacobian_params(q, names=names)[:, :3, :] if names else np.zeros((len(q), 3, 0))
    E = np.zeros((len(q), 3, 3 * n_points))
    E[:, :, 3 * point_col:3 * point_col + 3] = -np.eye(3)
    return np.concatenate([J, E], axis=2)


def _greedy_d_optimal(rows: np.ndarray, k: int) -> list[int]:
    """Pick ``k`` candidates maximising log det of the information matrix (regularised: unidentifiable
    directions stay unidentifiable whatever is picked, they must not dominate the choice)."""
    N, _, P = rows.shape
    scale = np.linalg.norm(rows.reshape(-1, P), axis=0)
    scale[scale < 1e-12] = 1.0
    A = rows / scale
    M = np.eye(P) * 1e-6 * N
    chosen: list[int] = []
    free = np.ones(N, bool)
    for _ in range(min(k, N)):
        Minv = np.linalg.inv(M)
        # det(M + Ai^T Ai) / det(M) = det(I + Ai Minv Ai^T)
        G = np.einsum("nip,pq,njq->nij", A, Minv, A)
        gain = np.linalg.slogdet(np.eye(3)[None] + G)[1]
        gain[~free] = -np.inf
        i = int(np.argmax(gain))
        chosen.append(i)
        free[i] = False
        M = M + A[i].T @ A[i]
    return chosen


def order_for_short_motion(model: Model, qs: np.ndarray, q_start: np.ndarray) -> list[int]:
    """Nearest-neighbour tour by move time (slowest joint), improved by 2-opt."""
    v = model.max_velocity

    def cost(a, b):
        return float(np.max(np.abs(a - b) / v))

    n = len(qs)
    if n <= 1:
        return list(range(n))
    left = set(range(n))
    cur = q_start
    tour: list[int] = []
    while left:
        i = min(left, key=lambda j: cost(cur, qs[j]))
        tour.append(i)
        left.remove(i)
        cur = qs[i]
    pts = [q_start] + [qs[i] for i in tour]
    improved = True
    passes = 0
    while improved and passes < 20:
        improved = False
        passes += 1
        for a in range(0, n - 1):
            for b in range(a + 2, n + 1):
                d0 = cost(pts[a], pts[a + 1]) + (cost(pts[b], pts[b + 1]) if b < n else 0.0)
                d1 = cost(pts[a], pts[b]) + (cost(pts[a + 1], pts[b + 1]) if b < n else 0.0)
                if d1 < d0 - 1e-9:
                    pts[a + 1:b + 1] = pts[a + 1:b + 1][::-1]
                    tour[a:b] = tour[a:b][::-1]
                    improved = True
    return tour


def n_unknowns(model: Model, identify: str, n_points: int) -> int:
    names = model.select(identify) if identify else []
    return len(names) + 3 * n_points


def generate_plan(model: Model, points: list[RefPoint], q_start, *, identify: str = "offsets",
                  n_fit: int | None = None, n_holdout: int = 4, cone_deg: float = 35.0, clearance: float = 0.03,
                  roll_deg: float = 150.0, margin_deg: float = 5.0, seed: int = 0,
                  candidates_per_point: int = 120) -> PosePlan:
    """A plan touching each of ``points`` from a spread of poses; ``n_fit`` defaults to max(20, twice the
    unknowns), spread over the points."""
    if not points:
        raise PlanError("pose plan: no reference point given")
    rng = np.random.default_rng(seed)
    q_start = np.asarray(q_start, float)
    names = model.select(identify) if identify else []
    unknowns = len(names) + 3 * len(points)
    n_fit = n_fit or max(20, 2 * unknowns)
    if 3 * n_fit <= unknowns:
        raise PlanError(f"pose plan: {n_fit} fit poses give {3 * n_fit} equations for {unknowns} unknowns")
    margin = np.deg2rad(margin_deg)
    all_q, all_a, all_rows, labels = [], [], [], []
    for k, pt in enumerate(points):
        q, qa = _candidates(model, pt, q_start, candidates_per_point, np.deg2rad(cone_deg), clearance,
                            np.deg2rad(roll_deg), margin, rng)
        if len(q) == 0:
            raise PlanError(f"pose plan: reference point {pt.label} at {np.round(pt.position * 1e3, 1).tolist()} mm "
                            f"is not reachable by model {model.name} within a {cone_deg:g} deg cone and joint limits")
        all_q.append(q)
        all_a.append(qa)
        all_rows.append(_info_rows(model, q, names, k, len(points)))
        labels += [pt.label] * len(q)
    Q, QA, rows = np.concatenate(all_q), np.concatenate(all_a), np.concatenate(all_rows)
    need = n_fit + n_holdout
    if len(Q) < need:
        raise PlanError(f"pose plan: only {len(Q)} feasible poses for {need} wanted (fit {n_fit} + holdout "
                        f"{n_holdout}); widen the cone or move the reference point")
    picked = _greedy_d_optimal(rows, need)
    fit, hold = picked[:n_fit], picked[n_fit:]
    # holdout poses: every point that is held out was also fitted (the solver needs its position)
    chosen = fit + hold
    qs = Q[chosen]
    tour = order_for_short_motion(model, qs, q_start)
    poses = []
    for i, t in enumerate(tour):
        c = chosen[t]
        poses.append(PlannedPose(i, labels[c], Q[c].tolist(), QA[c].tolist(), "fit" if t < n_fit else "holdout"))
    return PosePlan(poses, {"generated": True, "identify": identify, "n_fit": n_fit, "n_holdout": n_holdout,
                            "cone_deg": cone_deg, "clearance_m": clearance, "seed": seed,
                            "points": [p.to_dict() for p in points]})


def plan_from_joints(model: Model, entries: list[dict], points: dict[str, RefPoint], clearance: float = 0.03,
                     q_start=None) -> PosePlan:
    """A plan listed in a procedure: ``[{"point": "A", "q": [...rad...], "set": "fit"}, ...]``. The approach pose
    backs off along the point's approach direction."""
    poses = []
    for i, e in enumerate(entries):
        q = np.asarray(e["q"], float)
        if q.shape != (model.n_joints,) or not np.all(np.isfinite(q)):
            raise PlanError(f"listed pose {i}: expected {model.n_joints} finite joint values")
        if not model.within_limits(q)[0]:
            raise PlanError(f"listed pose {i}: outside the joint limits of {model.name}")
        pt = points[e.get("point", "A")]
        T = model.fk(q)
        T[:3, 3] += pt.approach * clearance
        full = model.n_joints >= 6
        r = model.ik(T if full else T[:3, 3], q, position_only=not full)
        if not r.ok[0]:
            raise PlanError(f"listed pose {i}: no approach pose {clearance * 1e3:g} mm back along the approach")
        poses.append(PlannedPose(i, pt.label, q.tolist(), r.q[0].tolist(), e.get("set", "fit")))
    if q_start is not None:
        tour = order_for_short_motion(model, np.array([p.q for p in poses]), np.asarray(q_start, float))
        poses = [poses[t] for t in tour]
        for i, p in enumerate(poses):
            p.index = i
    return PosePlan(poses, {"generated": False})


def generate_rotation_plan(model: Model, point: RefPoint, q_start, *, joint: int = -1, n_fit: int = 8,
                           n_holdout: int = 2, span_deg: float = 300.0, clearance: float = 0.03) -> PosePlan:
    """XYZR tool self-calibration (seed 003c): the rotary axis ``joint`` takes ``n_fit + n_holdout`` evenly
    spread angles; at each, the other joints put the nominal tip on ``point`` (position-only IK with the
    rotary joint held)."""
    j = joint % model.n_joints
    q_start = np.asarray(q_start, float)
    n = n_fit + n_holdout
    centre = float(np.clip(0.0, model.lower[j], model.upper[j]))
    half = min(np.deg2rad(span_deg) / 2, (model.upper[j] - model.lower[j]) / 2 - 1e-3)
    angles = np.linspace(centre - half, centre + half, n)
    W = np.ones(model.n_joints)
    W[j] = 0.0  # the rotary joint does not move in the IK: each pose keeps its angle
    seeds = np.repeat(q_start[None], n, axis=0)
    seeds[:, j] = angles
    res = model.ik(np.repeat(point.position[None], n, axis=0), seeds, position_only=True, weights=W)
    back = point.position + point.approach * clearance
    ra = model.ik(np.repeat(back[None], n, axis=0), res.q, position_only=True, weights=W)
    bad = np.flatnonzero(~(res.ok & ra.ok))
    if bad.size:
        raise PlanError(f"rotation plan: point {point.label} not reachable with joint {j + 1} at "
                        f"{np.rad2deg(angles[bad[0]]):.0f} deg")
    order = list(range(n))
    hold = set(np.linspace(1, n - 2, n_holdout).round().astype(int).tolist()) if n_holdout else set()
    poses = [PlannedPose(i, point.label, res.q[k].tolist(), ra.q[k].tolist(), "holdout" if k in hold else "fit")
             for i, k in enumerate(order)]
    return PosePlan(poses, {"generated": True, "rotation_joint": j + 1, "angles_rad": angles.tolist(),
                            "points": [point.to_dict()], "clearance_m": clearance})
