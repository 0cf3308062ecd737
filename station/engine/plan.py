"""Pose plans: which joint positions touch which reference point, in which order.

Generated from a reference point's approximate location and the nominal model: inverse kinematics over a
spread of tool orientations inside a cone around the approach direction (6-DOF arms) or from a spread of joint
seeds (4-DOF arms, position only), kept inside joint limits with a margin; from the feasible candidates a greedy
D-optimal choice on the identification Jacobian (the parameters to identify plus the unknown point positions)
picks enough poses for the unknowns, the next best become held-out poses, and a nearest-neighbour tour with
2-opt orders them for short motion. Or listed in the procedure (``plan_from_joints``).

Collision-aware: no link capsule of the arm may enter the cell's keep-out volumes or come below the mounting
plane (``station.kinematics.collision``). Candidates that do are dropped before the D-optimal choice, the
approach->touch path is checked, and so is every joint-space path between poses (from the start pose on),
sampled so that no point of the arm moves more than 5 mm between checks: the tour avoids blocked paths, a
path that stays blocked gets a via pose (``PlannedPose.via``), and when no via is found the plan is refused
with one line naming the link and the obstacle."""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from station.engine.cell import RefPoint
from station.kinematics import Model
from station.kinematics.collision import Box, Checker, Hit, KeepOut
from station.kinematics.se3 import frame_with_z
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
    via: list[list[float]] = field(default_factory=list)  # joint poses to pass through before approach_q

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


def _cone_dirs(axis: np.ndarray, cone: float, n: int, rng) -> np.ndarray:
    """``n`` unit vectors inside a cone of half-angle ``cone`` around ``axis`` (area-uniform)."""
    tilt = np.arccos(1 - rng.random(n) * (1 - np.cos(cone)))
    az = rng.random(n) * 2 * np.pi
    R = frame_with_z(axis, 0.0)
    local = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    return local @ R.T


def _facing(model: Model, q_start: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The start posture with the first joint turned so the tool is nearest ``target``: an arm reaches a point
    behind it by turning its base, not by folding its shoulder down through the table."""
    if not model.joints[0].revolute:
        return q_start.copy()
    turns = np.linspace(-np.pi, np.pi, 73)
    Q = np.repeat(q_start[None], len(turns), axis=0)
    Q[:, 0] = np.clip(q_start[0] + turns, model.lower[0], model.upper[0])
    return Q[int(np.argmin(np.linalg.norm(model.position(Q) - target, axis=1)))]


def _seeds(model: Model, q_start: np.ndarray, n: int, rng, target: np.ndarray | None = None) -> np.ndarray:
    lo = np.maximum(model.lower, -np.pi)
    hi = np.minimum(model.upper, np.pi)
    out = lo + (hi - lo) * rng.random((n, model.n_joints))
    centre = np.clip(q_start, model.lower, model.upper)
    if target is not None:
        centre = _facing(model, centre, target)
    out[0] = centre
    # half the seeds near the start posture (turned towards the point): arms reach the cell mostly in the
    # configuration they stand in
    k = n // 2
    out[1:k] = np.clip(centre + rng.normal(0, 0.6, (k - 1, model.n_joints)), lo, hi)
    return out


def _candidates(model: Model, point: RefPoint, q_start, n, cone, clearance, roll, margin, rng,
                checker: Checker | None = None, rejected: Counter | None = None):
    """Feasible (touch q, approach q) pairs for one point; with a ``checker``, only those whose touch pose,
    approach pose and the path between them keep every link clear (the reasons of the others are counted in
    ``rejected``)."""
    full = model.n_joints >= 6
    p = point.position
    back = p + point.approach * clearance
    if full:
        dirs = _cone_dirs(-point.approach, cone, n, rng)
        rolls = rng.uniform(-roll, roll, n)
        T = np.repeat(np.eye(4)[None], n, axis=0)
        for i in range(n):
            T[i, :3, :3] = frame_with_z(dirs[i], rolls[i])
        T[:, :3, 3] = p
        # every target from three seeds: the start posture turned towards the point and two random ones. All
        # converged solutions are candidates: the arm's other configurations (shoulder back, wrist flipped)
        # are what separates the zeros of parallel joints, and the keep-outs forbid some of them
        seeds = _seeds(model, q_start, 6, rng, p)[[0, 3, 4]]
        T = np.concatenate([T] * len(seeds))  # one batch, seed-major: the IK's rows are independent
        res = model.ik(T, np.repeat(seeds, n, axis=0), max_iter=120)
        q_touch, ok = res.q, res.ok
        Ta = T.copy()
        Ta[:, :3, 3] = back
        ra = model.ik(Ta, q_touch, max_iter=80)
    else:
        seeds = _seeds(model, q_start, n, rng)  # position only: seeds around the start as they are
        res = model.ik(np.repeat(p[None], n, axis=0), seeds, position_only=True, max_iter=150)
        q_touch, ok = res.q, res.ok
        ra = model.ik(np.repeat(back[None], n, axis=0), q_touch, position_only=True, max_iter=80)
        if ok.any():  # keep the tool pointing into the cone: the axis of the tool frame best aligned inward
            R = model.fk(q_touch)[:, :3, :3]
            align = np.einsum("nij,i->nj", R, -point.approach)  # cos between each tool axis and the inward dir
            axis = np.argmax(np.abs(np.median(align[ok], axis=0)))
            sign = np.sign(np.median(align[ok, axis]))
            ok &= sign * align[:, axis] >= np.cos(cone)
    q_touch, q_back = _near_start(model, q_start, q_touch, ra.q)
    ok &= ra.ok & _inside(model, q_touch, margin) & _inside(model, q_back, margin)
    ok &= np.max(np.abs(q_back - q_touch), axis=1) < 0.6  # no configuration flip between approach and touch
    q_touch, q_app = q_touch[ok], q_back[ok]
    _, first = np.unique(np.round(q_touch, 4), axis=0, return_index=True)  # the same solution from two seeds
    first.sort()
    q_touch, q_app = q_touch[first], q_app[first]
    if checker is None or not len(q_touch):
        return q_touch, q_app
    clear = checker.clear(q_touch) & checker.clear(q_app)
    clear[clear] = checker.paths_clear(q_app[clear], q_touch[clear])
    if rejected is not None and not clear.all():
        bad = np.flatnonzero(~clear)
        for i, ht, ha in zip(bad, checker.hits(q_touch[bad]), checker.hits(q_app[bad]), strict=True):
            h = ht or ha or checker.path_hit(q_app[i], q_touch[i])
            rejected[(h.link, h.link_name, h.obstacle)] += 1
    return q_touch[clear], q_app[clear]


def _near_start(model: Model, q_start, q: np.ndarray, qa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Revolute joints with more than a turn of range: the same pose with each angle a whole turn nearer the
    start where the limits allow (IK may land a turn away: the robot would swing a full turn to get there)."""
    q, qa = q.copy(), qa.copy()
    for j, jt in enumerate(model.joints):
        if not jt.revolute:
            continue
        k = np.round((q_start[j] - q[:, j]) / (2 * np.pi))
        shift = 2 * np.pi * k
        fits = ((q[:, j] + shift >= jt.lower) & (q[:, j] + shift <= jt.upper)
                & (qa[:, j] + shift >= jt.lower) & (qa[:, j] + shift <= jt.upper))
        q[fits, j] += shift[fits]
        qa[fits, j] += shift[fits]
    return q, qa


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


def order_for_short_motion(model: Model, qs: np.ndarray, q_start: np.ndarray,
                           blocked: set[frozenset] | None = None) -> list[int]:
    """Nearest-neighbour tour by move time (slowest joint), improved by 2-opt. ``blocked``: pairs of pose
    indices (-1 = the start) whose straight joint path collides; the tour uses them only when it must."""
    v = model.max_velocity
    penalty = 1e3 * (1.0 + float(np.max(np.abs(np.ptp(np.vstack([qs, q_start[None]]), axis=0)) / v)))
    blocked = blocked or set()

    def cost(i, j):
        a = q_start if i < 0 else qs[i]
        b = q_start if j < 0 else qs[j]
        return float(np.max(np.abs(a - b) / v)) + (penalty if frozenset((i, j)) in blocked else 0.0)

    n = len(qs)
    if n <= 1:
        return list(range(n))
    left = set(range(n))
    cur = -1
    tour: list[int] = []
    while left:
        i = min(left, key=lambda j: cost(cur, j))
        tour.append(i)
        left.remove(i)
        cur = i
    pts = [-1] + tour
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
                    improved = True
    return pts[1:]


# ---- collision-free paths -----------------------------------------------------------------------------------
def keep_out_checker(model: Model, keep_out: KeepOut | None) -> Checker:
    """The collision checker of ``model``'s links against ``keep_out`` (None: the default mounting plane)."""
    return Checker(model, KeepOut.default() if keep_out is None else keep_out)


def transit_checker(model: Model, keep_out: KeepOut | None, slack: float = 0.0, points=()) -> Checker:
    """The checker of the moves between poses: the links as :func:`keep_out_checker`, and the tool's tip kept out
    of every obstacle and of the references ``points`` (only the approach to a reference brings the tip there)."""
    return Checker(model, KeepOut.default() if keep_out is None else keep_out, slack=slack, tip=True,
                   tip_only=tuple(reference_body(p) for p in points))


REFERENCE_DEPTH = 0.03  # m: how far below a reference point its body (socket, nest, needle post) is kept out


def reference_body(point: RefPoint) -> Box:
    """The volume a reference occupies, for the tip on moves between poses: a box under the point along its
    approach axis, as wide as its capture radius, its top at the point (where a seated ball's centre is)."""
    from station.kinematics.se3 import frame_with_z

    a = np.asarray(point.approach, float)
    w = max(float(point.radius), 0.005)
    return Box(f"reference {point.label}", np.asarray(point.position, float) - a * REFERENCE_DEPTH / 2,
               np.array([w, w, REFERENCE_DEPTH / 2]), frame_with_z(a), clearance=0.0)


def _via_candidates(a: np.ndarray, b: np.ndarray, home: np.ndarray | None) -> np.ndarray:
    """Intermediate poses worth trying between ``a`` and ``b``: the home/start pose, and the joint-wise splits
    (move the proximal joints first, or the distal ones: e.g. lift the elbow before swinging the base)."""
    n = len(a)
    out = [home] if home is not None else []
    for k in range(1, n):
        out.append(np.concatenate([b[:k], a[k:]]))
        out.append(np.concatenate([a[:k], b[k:]]))
        if home is not None:
            out.append(np.concatenate([a[:k], home[k:]]))
            out.append(np.concatenate([home[:k], b[k:]]))
    return np.array(out)


def _travel(model: Model, path: list[np.ndarray]) -> float:
    v = model.max_velocity
    return float(sum(np.max(np.abs(y - x) / v) for x, y in zip(path, path[1:], strict=False)))


VIA_MARGIN = np.deg2rad(5.0)  # rad: a retract via keeps this far inside every joint limit (the plan's default)


def _lifted(checker: Checker, q: np.ndarray, heights=(0.1, 0.2, 0.3)) -> list[np.ndarray]:
    """Retract poses: the tool moved straight away from the mounting plane (up, for a table arm) by
    ``heights``, same orientation where the arm has the joints for it."""
    model = checker.model
    mount = checker.keep_out.mounting
    up = mount.normal if mount is not None else np.array([0.0, 0.0, 1.0])
    full = model.n_joints >= 6
    T = np.repeat(model.fk(q)[None], len(heights), axis=0)
    T[:, :3, 3] += np.asarray(heights)[:, None] * up
    r = model.ik(T if full else T[:, :3, 3], q, position_only=not full, max_iter=150)
    # the IK may put a joint anywhere inside its limits; a via at the very limit is one a true arm (its zeros off
    # by the errors being calibrated) cannot reach, and one a robot's limit-dependent speed envelope slows to a
    # stop short of: keep the margin the plan's own poses keep
    inside = _inside(model, r.q, VIA_MARGIN)
    return [x for x, ok, w in zip(r.q, r.ok, inside, strict=True) if ok and w and np.max(np.abs(x - q)) < 1.5]


def find_via(checker: Checker, a, b, home=None) -> list[np.ndarray] | None:
    """Via poses (zero, one or two) that make ``a -> b`` collision-free along straight joint paths, the
    quickest found; None when none of the candidates works. Candidates: the home (start) pose, joint-wise
    splits of the move, and retract poses above ``a`` and ``b``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if checker.path_hit(a, b) is None:
        return []
    home = None if home is None else np.asarray(home, float)
    C = np.vstack([_via_candidates(a, b, home), *_lifted(checker, a), *_lifted(checker, b)])
    C = C[checker.clear(C)]
    if not len(C):
        return None
    model = checker.model
    first = checker.paths_clear(np.repeat(a[None], len(C), 0), C)
    second = checker.paths_clear(C, np.repeat(b[None], len(C), 0))
    one = [(_travel(model, [a, c, b]), i) for i, c in enumerate(C) if first[i] and second[i]]
    if one:
        return [C[min(one)[1]]]
    # two vias: from a to one that a reaches, on to one that reaches b
    pairs = sorted((_travel(model, [a, C[i], C[j], b]), i, j) for i in np.flatnonzero(first)
                   for j in np.flatnonzero(second) if i != j)
    for _, i, j in pairs[:40]:
        if checker.path_hit(C[i], C[j]) is None:
            return [C[i], C[j]]
    return None


def _blocked_message(what: str, hit: Hit) -> str:
    return f"{what}: {hit.describe()}, and no via pose avoids it; move the obstacle or the points"


def route(checker: Checker, q_from, targets: list, home=None, what: str = "move") -> list[np.ndarray]:
    """The joint poses to move through, from ``q_from`` over each of ``targets`` in turn, with via poses
    inserted where a straight joint path would bring a link into a keep-out. Raises ``PlanError`` (one line,
    naming the link and the obstacle) when a target itself is not clear or no via is found."""
    out: list[np.ndarray] = []
    cur = np.asarray(q_from, float)
    for t in targets:
        t = np.asarray(t, float)
        hit = checker.hits(t[None])[0]
        if hit is not None:
            raise PlanError(f"{what}: target {np.round(t, 4).tolist()} rad: {hit.describe()}")
        leg = checker.leaving(cur)
        via = find_via(leg, cur, t, home)
        if via is None:
            raise PlanError(_blocked_message(what, leg.path_hit(cur, t)))
        out += via + [t]
        cur = t
    return out


RUN_SLACK = 0.002  # m: at run time a move may come this much closer than the clearance the plan kept
_checkers: dict = {}


def route_from(model: Model, keep_out: KeepOut | None, q_now, targets: list, what: str = "move",
               points=()) -> list[np.ndarray]:
    """The run-time check before a plan's moves: :func:`route` from where the arm stands (a resumed or jogged
    arm may stand anywhere), with ``RUN_SLACK`` less clearance than the plan kept."""
    points = tuple(points)
    key = (id(model), id(keep_out), *map(id, points))
    if key not in _checkers:
        if len(_checkers) > 8:
            _checkers.clear()
        # the objects are kept with their checker: their ids stay valid as keys
        _checkers[key] = (model, keep_out, points, transit_checker(model, keep_out, RUN_SLACK, points))
    return route(_checkers[key][3], q_now, targets, what=what)


def _route_plan(model: Model, checker: Checker, poses: list[PlannedPose], q_start,
                known_clear: list[bool] | None = None) -> list[PlannedPose]:
    """Order-preserving: give each pose the vias its inter-pose path needs (from the previous approach pose,
    or the start). The start pose is the home for vias: the arm stood there. ``known_clear[i]``: the path into
    pose i was checked already."""
    prev = None if q_start is None else np.asarray(q_start, float)
    for i, p in enumerate(poses):
        if prev is not None and not (known_clear and known_clear[i]):
            leg = checker.leaving(prev)
            via = find_via(leg, prev, p.approach_arr, q_start)
            if via is None:
                frm = "the start pose" if i == 0 else f"pose {i - 1}"
                raise PlanError(_blocked_message(f"pose plan: path from {frm} to pose {i}",
                                                 leg.path_hit(prev, p.approach_arr)))
            p.via = [v.tolist() for v in via]
        prev = p.approach_arr
    return poses


def _scan_edges(checker: Checker, QA: np.ndarray, q_start: np.ndarray, ends: list) -> list[Hit | None]:
    """The worst hit on each approach-to-approach path ``ends`` (index -1: the start pose, whose paths leave
    from where the arm stands: ``Checker.leaving``)."""
    out: list[Hit | None] = [None] * len(ends)
    for ck, idx in ((checker, [k for k, (i, _) in enumerate(ends) if i >= 0]),
                    (checker.leaving(q_start), [k for k, (i, _) in enumerate(ends) if i < 0])):
        if idx:
            hits = ck.scan(np.array([q_start if ends[k][0] < 0 else QA[ends[k][0]] for k in idx]),
                           QA[[ends[k][1] for k in idx]])
            for k, h in zip(idx, hits, strict=True):
                out[k] = h
    return out


def _order_clear(model: Model, checker: Checker, QA: np.ndarray, q_start: np.ndarray,
                 qs: np.ndarray) -> tuple[list[int], list[bool]]:
    """Tour order (by ``qs``) that avoids blocked approach-to-approach paths where another order can; and per
    tour step, whether its path is known to be clear."""
    blocked: set[frozenset] = set()
    seen: set[frozenset] = set()
    tour = order_for_short_motion(model, qs, q_start)
    for _ in range(6):
        edges = [frozenset((a, b)) for a, b in zip([-1] + tour, tour, strict=False)]
        new = [e for e in edges if e not in seen]
        if not new:
            break
        ends = [sorted(e) for e in new]
        hits = _scan_edges(checker, QA, q_start, ends)
        for e, h in zip(new, hits, strict=True):
            seen.add(e)
            if h is not None:
                blocked.add(e)
        if not any(e in blocked for e in edges):
            break
        tour = order_for_short_motion(model, qs, q_start, blocked)
    edges = [frozenset((a, b)) for a, b in zip([-1] + tour, tour, strict=False)]
    return tour, [e in seen and e not in blocked for e in edges]


def _start_clear(checker: Checker, q_start) -> None:
    hit = checker.hits(np.asarray(q_start, float)[None])[0]
    if hit is not None:
        raise PlanError(f"pose plan: at the robot's current position {hit.describe()}; jog it clear first")


def _rejection_note(rejected: Counter) -> str:
    if not rejected:
        return ""
    (link, name, obstacle), k = rejected.most_common(1)[0]
    what = "the tool" if name == "tool" else f"link {link} ({name})"
    return f"; {sum(rejected.values())} candidate poses dropped, most because {what} enters '{obstacle}'"


def n_unknowns(model: Model, identify: str, n_points: int) -> int:
    names = model.select(identify) if identify else []
    return len(names) + 3 * n_points


def generate_plan(model: Model, points: list[RefPoint], q_start, *, identify: str = "offsets",
                  n_fit: int | None = None, n_holdout: int = 4, cone_deg: float = 35.0, clearance: float = 0.03,
                  roll_deg: float = 150.0, margin_deg: float = 5.0, seed: int = 0,
                  candidates_per_point: int = 120, keep_out: KeepOut | None = None) -> PosePlan:
    """A plan touching each of ``points`` from a spread of poses; ``n_fit`` defaults to max(20, twice the
    unknowns), spread over the points. ``keep_out``: the cell's (None: nothing below the base plane)."""
    if not points:
        raise PlanError("pose plan: no reference point given")
    rng = np.random.default_rng(seed)
    q_start = np.asarray(q_start, float)
    checker = keep_out_checker(model, keep_out)
    _start_clear(checker, q_start)
    rejected: Counter = Counter()
    names = model.select(identify) if identify else []
    unknowns = len(names) + 3 * len(points)
    n_fit = n_fit or max(20, 2 * unknowns)
    if 3 * n_fit <= unknowns:
        raise PlanError(f"pose plan: {n_fit} fit poses give {3 * n_fit} equations for {unknowns} unknowns")
    margin = np.deg2rad(margin_deg)
    all_q, all_a, all_rows, labels = [], [], [], []
    for k, pt in enumerate(points):
        mine: Counter = Counter()
        q, qa = _candidates(model, pt, q_start, candidates_per_point, np.deg2rad(cone_deg), clearance,
                            np.deg2rad(roll_deg), margin, rng, checker, mine)
        rejected += mine
        if len(q) == 0:
            raise PlanError(f"pose plan: reference point {pt.label} at {np.round(pt.position * 1e3, 1).tolist()} mm "
                            f"is not reachable by model {model.name} within a {cone_deg:g} deg cone and joint limits"
                            + (" clear of the keep-outs" if mine else "") + _rejection_note(mine))
        all_q.append(q)
        all_a.append(qa)
        all_rows.append(_info_rows(model, q, names, k, len(points)))
        labels += [pt.label] * len(q)
    Q, QA, rows = np.concatenate(all_q), np.concatenate(all_a), np.concatenate(all_rows)
    need = n_fit + n_holdout
    if len(Q) < need:
        raise PlanError(f"pose plan: only {len(Q)} feasible poses for {need} wanted (fit {n_fit} + holdout "
                        f"{n_holdout}); widen the cone or move the reference point" + _rejection_note(rejected))
    picked = _greedy_d_optimal(rows, need)
    fit, hold = picked[:n_fit], picked[n_fit:]
    # holdout poses: every point that is held out was also fitted (the solver needs its position)
    chosen = fit + hold
    qs = Q[chosen]
    transit = transit_checker(model, keep_out, points=points)
    tour, known = _order_clear(model, transit, QA[chosen], q_start, qs)
    poses = []
    for i, t in enumerate(tour):
        c = chosen[t]
        poses.append(PlannedPose(i, labels[c], Q[c].tolist(), QA[c].tolist(), "fit" if t < n_fit else "holdout"))
    _route_plan(model, transit, poses, q_start, known)
    return PosePlan(poses, {"generated": True, "identify": identify, "n_fit": n_fit, "n_holdout": n_holdout,
                            "cone_deg": cone_deg, "clearance_m": clearance, "seed": seed,
                            "points": [p.to_dict() for p in points], "keep_out": checker.keep_out.to_dict(),
                            "rejected_for_collision": sum(rejected.values())})


def plan_from_joints(model: Model, entries: list[dict], points: dict[str, RefPoint], clearance: float = 0.03,
                     q_start=None, keep_out: KeepOut | None = None) -> PosePlan:
    """A plan listed in a procedure: ``[{"point": "A", "q": [...rad...], "set": "fit"}, ...]``. The approach pose
    backs off along the point's approach direction. A listed pose that brings a link into a keep-out (or
    whose approach does) is refused."""
    checker = keep_out_checker(model, keep_out)
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
        for which, qq in (("", q), (" (its approach pose)", r.q[0])):
            hit = checker.hits(qq[None])[0]
            if hit is not None:
                raise PlanError(f"listed pose {i}{which}: {hit.describe()}")
        hit = checker.path_hit(r.q[0], q)
        if hit is not None:
            raise PlanError(f"listed pose {i}: on the approach {hit.describe()}")
        poses.append(PlannedPose(i, pt.label, q.tolist(), r.q[0].tolist(), e.get("set", "fit")))
    if q_start is not None:
        _start_clear(checker, q_start)
        transit = transit_checker(model, keep_out, points=points.values())
        tour, known = _order_clear(model, transit, np.array([p.approach_q for p in poses]),
                                   np.asarray(q_start, float), np.array([p.q for p in poses]))
        poses = [poses[t] for t in tour]
        for i, p in enumerate(poses):
            p.index = i
    _route_plan(model, transit_checker(model, keep_out, points=points.values()), poses, q_start,
                known if q_start is not None else None)
    return PosePlan(poses, {"generated": False, "keep_out": checker.keep_out.to_dict()})


def generate_rotation_plan(model: Model, point: RefPoint, q_start, *, joint: int = -1, n_fit: int = 8,
                           n_holdout: int = 2, span_deg: float = 300.0, clearance: float = 0.03,
                           keep_out: KeepOut | None = None) -> PosePlan:
    """XYZR tool self-calibration (tcp_circle): the rotary axis ``joint`` takes ``n_fit + n_holdout`` evenly
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
    checker = keep_out_checker(model, keep_out)
    _start_clear(checker, q_start)
    for k in range(n):
        hit = checker.hits(res.q[k][None])[0] or checker.hits(ra.q[k][None])[0] or checker.path_hit(ra.q[k], res.q[k])
        if hit is not None:
            raise PlanError(f"rotation plan: with joint {j + 1} at {np.rad2deg(angles[k]):.0f} deg {hit.describe()}")
    order = list(range(n))
    hold = set(np.linspace(1, n - 2, n_holdout).round().astype(int).tolist()) if n_holdout else set()
    poses = [PlannedPose(i, point.label, res.q[k].tolist(), ra.q[k].tolist(), "holdout" if k in hold else "fit")
             for i, k in enumerate(order)]
    _route_plan(model, transit_checker(model, keep_out, points=[point]), poses, q_start)
    return PosePlan(poses, {"generated": True, "rotation_joint": j + 1, "angles_rad": angles.tolist(),
                            "points": [point.to_dict()], "clearance_m": clearance,
                            "keep_out": checker.keep_out.to_dict()})
