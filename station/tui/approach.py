"""Bringing the tool to a reference point by hand: how far the tool is from the selected point (the proximity
cue), a planned move to a standoff above it ("go near"), and which points this arm can be sent to at all.

Everything here is the **nominal** model (what the station believes before the calibration) and the cell
file's approximate point positions: the cue says where to jog, the touch indicator says when it touches. The
planned move is collision-checked like every plan (``station.engine.plan.route_from``: keep-out volumes and
mounting plane along the joint path, via poses where needed) and runs at the manual-jog speed rules of
``station.robot.motion`` (the tool at or below the speed override, never above 250 mm/s)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.kinematics import se3
from station.robot.errors import LimitError
from station.robot.motion import MANUAL_TOOL_SPEED_CAP, joint_speed_for_tool_cap

NEAR_STANDOFF = 0.02  # m: "go near" ends this far from the point, along its approach direction
NEAR_CONE = np.deg2rad(35.0)  # a tool axis within this of the point's inward direction keeps its orientation
NEAR_ENTRY = 0.05  # m: extra distance of the entry pose when the direct path would sweep close to the point
NEAR_CLEAR = 0.75  # on the way, the tool stays at least this share of the standoff away from the point
NEAR_JOINT_SPEED = np.deg2rad(30.0)  # rad/s per joint, as every manual jog (station.tui.controller)
NEEDLE_FINE = 0.002  # m: near a needle, say so: its contact closes within tens of micrometres


@dataclass(frozen=True)
class Target:
    """A point the technician can be guided to: a cell point (socket/needle, approach direction, radius) or a
    ``--reference`` position (no kind: approached from above the mounting plane)."""

    label: str
    kind: str  # "socket" | "needle" | "reference"
    position: np.ndarray  # m, robot base frame (approximate)
    approach: np.ndarray  # unit vector from the point towards where the tool comes from
    radius: float | None = None  # m: a socket's capture radius, a needle's contact radius


def targets_of(cell, reference, up: np.ndarray | None = None) -> dict[str, Target]:
    """Every point with a nominal position: the cell's, then ``--reference`` labels the cell lacks."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float)
    out: dict[str, Target] = {}
    if cell is not None:
        for p in cell.points.values():
            a = np.asarray(p.approach, float)
            out[p.label] = Target(p.label, p.kind, np.asarray(p.position, float), a / np.linalg.norm(a), p.radius)
    if isinstance(reference, dict):
        for label, xyz in reference.items():
            if label not in out:
                out[label] = Target(label, "reference", np.asarray(xyz, float), up)
    return out


@dataclass(frozen=True)
class Proximity:
    """Where the tool (nominal model) is relative to a point. ``delta`` is the move that would bring the tool
    onto the point, in the axes of ``frame`` (base or tool); ``above`` the height over the point along its
    approach direction (negative: past it), ``lateral`` the distance from the approach axis."""

    label: str
    kind: str
    distance: float
    above: float
    lateral: float
    delta: np.ndarray
    frame: str
    radius: float | None

    @property
    def within(self) -> bool:
        """Inside the socket's capture radius / the needle's contact radius (nominal: the truth may differ)."""
        return self.radius is not None and self.distance <= self.radius


def proximity(T: np.ndarray, target: Target, frame: str = "base") -> Proximity:
    """Proximity of the tool pose ``T`` (4x4, nominal forward kinematics) to ``target``."""
    d = target.position - T[:3, 3]  # tool -> point, base frame
    above = float(-d @ target.approach)
    lateral = float(np.linalg.norm(-d - above * target.approach))
    delta = T[:3, :3].T @ d if frame == "tool" else d
    return Proximity(target.label, target.kind, float(np.linalg.norm(d)), above, lateral, delta, frame,
                     target.radius)


@dataclass
class NearPlan:
    """A planned move to ``standoff`` from the point along its approach: joint poses to pass through (via
    poses, an entry pose, the goal) and the lead-joint speed of each segment."""

    label: str
    path: list[np.ndarray]
    speeds: list[float]
    goal: np.ndarray  # 4x4 tool pose at the end (nominal)
    standoff: float
    cap: float  # m/s at the tool
    seconds: float  # at the speeds above, without accelerations
    travel: float  # m: tool path length (nominal, sampled)
    reoriented: bool  # the tool turned to point into the approach direction
    notes: list[str] = field(default_factory=list)
    start: np.ndarray | None = None  # joint positions the plan starts from


def _goal(model, T: np.ndarray, target: Target, standoff: float) -> tuple[np.ndarray, bool]:
    """Tool pose at the standoff: the current orientation if the tool axis (z) already points into the
    approach cone, else the smallest rotation that makes it point along the approach (roll kept)."""
    goal = T.copy()
    goal[:3, 3] = target.position + target.approach * standoff
    if model.n_joints < 6:
        return goal, False  # position only: the arm cannot choose its orientation freely
    z, want = T[:3, 2], -target.approach
    angle = float(np.arccos(np.clip(z @ want, -1.0, 1.0)))
    if angle <= NEAR_CONE:
        return goal, False
    axis = np.cross(z, want)
    if np.linalg.norm(axis) < 1e-9:  # pointing straight away: turn about any axis normal to it
        axis = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    goal[:3, :3] = se3.rotvec_to_matrix(axis / np.linalg.norm(axis) * angle) @ T[:3, :3]
    return goal, True


def _seeds(model, q: np.ndarray, goal_xyz: np.ndarray) -> np.ndarray:
    """IK seeds: where the arm stands, the same posture with the first joint turned so the tool is nearest the
    goal (an arm reaches round by turning its base), and a few fixed perturbations of both."""
    seeds = [q]
    if model.joints[0].revolute:
        turns = np.linspace(-np.pi, np.pi, 73)
        Q = np.repeat(q[None], len(turns), axis=0)
        Q[:, 0] = np.clip(q[0] + turns, model.lower[0], model.upper[0])
        seeds.append(Q[int(np.argmin(np.linalg.norm(model.position(Q) - goal_xyz, axis=1)))])
    rng = np.random.default_rng(0)
    for base in list(seeds):
        for _ in range(3):
            seeds.append(np.clip(base + rng.normal(0.0, 0.3, len(q)), model.lower, model.upper))
    return np.array(seeds)


def _ik_goal(model, q: np.ndarray, goal: np.ndarray, checker) -> np.ndarray | None:
    """The joint solution for ``goal`` (4x4, or several (k,4,4) of which any will do) nearest the arm's posture
    (joint travel in time at the joints' speed limits) that keeps every link clear; None when there is none."""
    full = model.n_joints >= 6
    goals = goal.reshape(-1, 4, 4)
    seeds = _seeds(model, q, goals[0, :3, 3])
    tgt = np.repeat(goals, len(seeds), axis=0)
    res = model.ik(tgt if full else tgt[:, :3, 3], np.tile(seeds, (len(goals), 1)), position_only=not full,
                   max_iter=150)
    cand = res.q[res.ok]
    if not len(cand):
        return None
    cand = cand[np.all((cand >= model.lower) & (cand <= model.upper), axis=1)]
    if checker is not None and len(cand):
        cand = cand[checker.clear(cand)]
    if not len(cand):
        return None
    cost = np.max(np.abs(cand - q) / model.max_velocity, axis=1)
    return cand[int(np.argmin(cost))]


def _closest(model, a: np.ndarray, b: np.ndarray, point: np.ndarray, n: int = 400) -> float:
    """Nearest approach of the tool to ``point`` on the straight joint path a -> b (nominal, sampled)."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    return float(np.min(np.linalg.norm(model.position(a + s * (b - a)) - point, axis=1)))


def _distance(model, q: np.ndarray, target: Target) -> float:
    return float(np.linalg.norm(model.position(q[None])[0] - target.position))


def _tool_travel(model, path: list[np.ndarray], n: int = 24) -> float:
    total = 0.0
    for a, b in zip(path, path[1:], strict=False):
        s = np.linspace(0.0, 1.0, n)[:, None]
        p = model.position(a + s * (b - a))
        total += float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    return total


def plan_near(model, keep_out, q_now: np.ndarray, target: Target, cap: float, *, standoff: float = NEAR_STANDOFF,
              checker=None) -> NearPlan:
    """Plan "go near ``target``": joint poses from ``q_now`` to the tool at ``standoff`` from the point along its
    approach direction, each straight joint segment clear of the keep-out (via poses where needed, as every
    plan) and never sweeping the tool closer to the point than the standoff allows; speeds at the tool cap
    ``cap`` (m/s, at most 250 mm/s). Raises LimitError (one line, nothing moves) when it cannot."""
    from station.engine.plan import PlanError, route_from
    from station.kinematics.collision import Checker

    cap = float(min(cap, MANUAL_TOOL_SPEED_CAP))
    if checker is None and getattr(model, "kind", "serial") != "parallel":
        checker = Checker(model, keep_out)
    q_now = np.asarray(q_now, float)
    T = model.fk(q_now)
    goal, turned = _goal(model, T, target, standoff)
    what = f"go near {target.label}"
    q_goal = _ik_goal(model, q_now, goal, checker)
    if q_goal is None:
        raise LimitError(f"{what}: the nominal model cannot put the tool {standoff * 1e3:g} mm above "
                         f"{target.label} within joint limits and clear of the keep-out; jog closer first")
    notes: list[str] = []
    targets = [q_goal]
    keep = standoff * NEAR_CLEAR
    if _closest(model, q_now, q_goal, target.position) < min(keep, _distance(model, q_now, target)):
        # the straight joint path would sweep the tool past the point: come in along the approach instead
        entry, _ = _goal(model, goal, target, standoff + NEAR_ENTRY)
        q_entry = _ik_goal(model, q_goal, entry, checker)
        if q_entry is None:
            raise LimitError(f"{what}: the path would sweep the tool across the point and the arm cannot reach "
                             f"an entry pose {(standoff + NEAR_ENTRY) * 1e3:g} mm out; jog the tool above it first")
        targets = [q_entry, q_goal]
        notes.append(f"enters along the approach from {(standoff + NEAR_ENTRY) * 1e3:g} mm out")
    try:
        path = route_from(model, keep_out, q_now, targets, what=what)
    except PlanError as e:
        raise LimitError(str(e)) from None
    # on every segment (via poses too) the tool stays out of the sphere of ``keep`` round the point, or at least
    # comes no closer than where that segment starts (a tool starting on the point may leave it)
    prev = q_now
    for q in path:
        if _closest(model, prev, q, target.position) < min(keep, _distance(model, prev, target)) - 1e-4:
            raise LimitError(f"{what}: the path would sweep the tool across the point (closer than "
                             f"{keep * 1e3:.0f} mm on the way); jog the tool out above it first")
        prev = q
    speeds, seconds, prev = [], 0.0, q_now
    for q in path:
        v = joint_speed_for_tool_cap(model, prev, q, NEAR_JOINT_SPEED, cap=cap)
        speeds.append(v)
        seconds += float(np.max(np.abs(q - prev))) / v if v > 0 else 0.0
        prev = q
    if len(path) > len(targets):
        notes.append(f"{len(path) - len(targets)} via pose(s) round the keep-out")
    return NearPlan(target.label, path, speeds, goal, standoff, cap, seconds, _tool_travel(model, [q_now, *path]),
                    turned, notes, q_now)


def reach_problem(model, target: Target, checker=None, q_hint: np.ndarray | None = None) -> str | None:
    """Why the nominal arm cannot bring its tool onto ``target`` (tool axis into the approach direction, every
    link clear), or None when it can. Used so that guidance never sends the technician to such a point."""
    q = np.clip(np.zeros(model.n_joints) if q_hint is None else np.asarray(q_hint, float), model.lower, model.upper)
    T = np.eye(4)
    if model.n_joints >= 6:
        z = -target.approach
        x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
        x /= np.linalg.norm(x)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = target.position
    rolls = np.linspace(0.0, 2 * np.pi, 6, endpoint=False) if model.n_joints >= 6 else [0.0]
    goals = np.array([T @ _rz(r) for r in rolls])  # any roll about the approach will do
    if _ik_goal(model, q, goals, checker) is None:
        return "out of reach of the nominal model (tool pointing into its approach, links clear)"
    return None


def _rz(angle: float) -> np.ndarray:
    R = np.eye(4)
    R[:3, :3] = se3.rotvec_to_matrix([0.0, 0.0, angle])
    return R


@dataclass
class NearMove:
    """A running "go near": the plan and which segment is under way (the controller starts each segment
    with ``move_joints(..., wait=False)`` and the next one when the arm stands at the previous target)."""

    plan: NearPlan
    index: int = 0
    started: float = 0.0  # monotonic time the current segment was commanded
    seen_moving: bool = False

    @property
    def segment(self) -> np.ndarray:
        return self.plan.path[self.index]

    @property
    def speed(self) -> float:
        return self.plan.speeds[self.index]

    @property
    def last(self) -> bool:
        return self.index >= len(self.plan.path) - 1
