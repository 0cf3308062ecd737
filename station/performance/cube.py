"""The ISO 9283 test cube and its poses, from the robot's model and the cell's keep-outs.

The standard places a cube in the part of the workspace with the greatest anticipated use, of the largest
volume the workspace allows, with edges parallel to the base frame; the test poses lie on one of the cube's
diagonal planes (a plane through two opposite edges): P1 at the intersection of the plane's diagonals (the
cube's centre), P2..P5 on the diagonals at 10 % of the diagonal's length from the plane's corners (docs/iso9283.md
names the sources). Here the cube is centred where the technician left the tool (the area of greatest use) and
the tool keeps the orientation it had there; its edge is the largest for which every probe point of the cube
(corners, edge middles, face centres), every test and registration pose and every approach pose is reachable
in the arm's present configuration branch, off the joint limits, away from singularities and clear of the
mounting plane and keep-outs. The cube can also be given (centre and edge).

Plane names: the two edges a diagonal plane contains are parallel to one base axis; ``x+`` holds the x-parallel
edges at (y, z) = (-, -) and (+, +), ``x-`` those at (+, -) and (-, +); likewise ``y+``, ``y-`` (edges along y,
in x and z) and ``z+``, ``z-`` (vertical edges, in x and y)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.kinematics import se3

FRACTION = 0.10  # P2..P5 sit this fraction of the diagonal in from the plane's corners
REGISTRATION_INSET = 0.8  # registration poses: the cube's corners pulled in to 80 % of the half edge
APPROACH = 0.01  # m: an approach pose this far back along the approach direction
JOINT_MARGIN = np.radians(5.0)  # rad (m for a prismatic joint: PRISMATIC_MARGIN) from every joint limit
PRISMATIC_MARGIN = 0.005
BRANCH = 2.0  # rad: no joint may turn further than this from its value at the centre (no configuration flip)
# every joint turns at least this much on the last motion onto a pose (m for a prismatic joint: PRELOAD_LENGTH), so
# its gear backlash is taken up on the same side every time, also for a joint the approach direction hardly turns
PRELOAD = np.radians(0.2)
PRELOAD_LENGTH = 0.5e-3
MIN_CONDITION = 0.02  # smallest / largest singular value of the Jacobian (rotation rows in ROTATION_LENGTH)
ROTATION_LENGTH = 0.3  # m per rad: weighs the Jacobian's rotation rows against its position rows
PLANES = ("x+", "x-", "y+", "y-", "z+", "z-")
DIRECTIONS = {"+x": (1.0, 0, 0), "+y": (0, 1.0, 0), "+z": (0, 0, 1.0), "-x": (-1.0, 0, 0), "-y": (0, -1.0, 0),
              "-z": (0, 0, -1.0)}  # approach from this side: the approach pose is APPROACH along it


class CubeError(ValueError):
    """No test cube fits (one line: what is in the way)."""


def _plane_corners(plane: str) -> np.ndarray:
    """The plane's four corners on the unit cube [-1, 1]^3, in order around the plane (1-3 and 2-4 opposite)."""
    if plane not in PLANES:
        raise CubeError(f"plane {plane!r}: expected one of {', '.join(PLANES)}")
    axis = "xyz".index(plane[0])
    u, v = [k for k in range(3) if k != axis]
    s = 1.0 if plane[1] == "+" else -1.0
    out = []
    for t, w in ((-1, -1), (1, -1), (1, 1), (-1, 1)):  # along the edge t, across w
        p = np.zeros(3)
        p[axis], p[u], p[v] = t, w, s * w
        out.append(p)
    return np.array(out)


@dataclass
class TestCube:
    __test__ = False  # not a pytest test class

    centre: np.ndarray  # (3,) m, base frame
    edge: float  # m
    rotation: np.ndarray  # (3, 3): the tool orientation of every test pose
    plane: str = "x+"
    notes: list[str] = field(default_factory=list)

    def corners(self) -> np.ndarray:
        g = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], float)
        return self.centre + g * self.edge / 2

    def test_positions(self) -> dict[str, np.ndarray]:
        """P1 (the centre) and P2..P5 at ``FRACTION`` of the diagonals from the plane's corners; P2/P4 and
        P3/P5 are opposite."""
        q = self.centre + _plane_corners(self.plane) * self.edge / 2
        out = {"P1": self.centre.copy()}
        for k in range(4):
            out[f"P{k + 2}"] = q[k] + FRACTION * (q[(k + 2) % 4] - q[k])
        return out

    def registration_positions(self) -> dict[str, np.ndarray]:
        """Where the instrument's frame is registered: the cube's corners pulled in (C1..C8)."""
        g = self.corners() - self.centre
        return {f"C{k + 1}": self.centre + REGISTRATION_INSET * g[k] for k in range(8)}

    def probe_positions(self) -> np.ndarray:
        """The 27 points of the cube's 3x3x3 grid: corners, edge middles, face centres, centre."""
        g = np.array([[x, y, z] for z in (-1, 0, 1) for y in (-1, 0, 1) for x in (-1, 0, 1)], float)
        return self.centre + g * self.edge / 2

    def pose(self, position, direction: str | None = None, distance: float = APPROACH) -> np.ndarray:
        """The tool pose (4x4) at ``position``, or its approach pose ``distance`` back along ``direction``."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = np.asarray(position, float) + (0 if direction is None else distance * np.asarray(
            DIRECTIONS[direction]))
        return T

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "edge": float(self.edge), "plane": self.plane,
                "rotation": se3.matrix_to_rotvec(self.rotation).tolist(), "units": "m, rad (rotation vector)",
                "notes": list(self.notes)}

    @classmethod
    def from_dict(cls, d: dict) -> TestCube:
        return cls(np.asarray(d["centre"], float), float(d["edge"]), se3.rotvec_to_matrix(
            np.asarray(d["rotation"], float)), str(d.get("plane", "x+")), list(d.get("notes") or []))


@dataclass
class Reach:
    """IK of a set of tool poses in one configuration branch: joint values and, per pose, why it is not usable
    (None: usable)."""

    q: np.ndarray
    why: list[str | None]

    @property
    def ok(self) -> bool:
        return all(w is None for w in self.why)


def _full(model) -> bool:
    return model.n_joints >= 6


def reach(model, poses: np.ndarray, q_ref: np.ndarray, checker=None) -> Reach:
    """IK of ``poses`` ``(N, 4, 4)`` from ``q_ref`` (full pose for a 6+ axis arm, position for fewer), each
    checked: converged, ``JOINT_MARGIN`` off the limits, within ``BRANCH`` of ``q_ref``, conditioned, clear of
    ``checker``'s keep-outs."""
    poses = np.asarray(poses, float).reshape(-1, 4, 4)
    full = _full(model)
    res = model.ik(poses if full else poses[:, :3, 3], q_ref, position_only=not full, tol_pos=1e-9, tol_rot=1e-9,
                   max_iter=300)
    q = res.q
    margin = np.array([JOINT_MARGIN if j.revolute else PRISMATIC_MARGIN for j in model.joints])
    why: list[str | None] = [None] * len(q)
    T, Jq, _ = model.jacobians(q)
    J = Jq if full else Jq[:, :3]
    if full:
        J = np.concatenate([J[:, :3], J[:, 3:] * ROTATION_LENGTH], axis=1)
    sv = np.linalg.svd(J, compute_uv=False)
    cond = sv[:, -1] / np.maximum(sv[:, 0], 1e-300)
    hits = checker.hits(q) if checker is not None else [None] * len(q)
    for i in range(len(q)):
        if not (res.position_error[i] < 1e-6 and res.orientation_error[i] < 1e-6):
            why[i] = "out of reach"
        elif np.any(q[i] < model.lower + margin) or np.any(q[i] > model.upper - margin):
            k = int(np.argmax((q[i] < model.lower + margin) | (q[i] > model.upper - margin)))
            why[i] = f"joint {k + 1} within {np.degrees(margin[k]):.0f} deg of its limit"
        elif np.max(np.abs(q[i] - q_ref)) > BRANCH:
            why[i] = "only in another configuration (a joint turns more than 115 deg)"
        elif cond[i] < MIN_CONDITION:
            why[i] = "near a singularity"
        elif hits[i] is not None:
            why[i] = f"a link meets {hits[i].describe()}"
    return Reach(q, why)


@dataclass
class Plan:
    """Joint values of everything the test visits: ``poses[name]`` the pose, ``approach[name][direction]`` its
    approach pose."""

    cube: TestCube
    poses: dict[str, np.ndarray]
    approach: dict[str, dict[str, np.ndarray]]


def _needed(cube: TestCube, directions: dict[str, tuple[str, ...]]) -> list[tuple[str, str | None, np.ndarray]]:
    """(name, approach direction or None, tool pose) of everything the test visits, and the cube's grid."""
    named = {**cube.test_positions(), **cube.registration_positions()}
    out = []
    for name, p in named.items():
        out.append((name, None, cube.pose(p)))
        for d in directions.get(name, directions.get("*", ())):
            out.append((name, d, cube.pose(p, d)))
    out += [(f"grid{k}", None, cube.pose(p)) for k, p in enumerate(cube.probe_positions())]
    return out


def plan_cube(model, cube: TestCube, q_centre: np.ndarray, directions: dict[str, tuple[str, ...]],
              checker=None) -> tuple[Plan | None, str | None]:
    """The joint values for ``cube``, or ``(None, why)`` naming the first pose that is not usable."""
    need = _needed(cube, directions)
    r = reach(model, np.array([T for *_, T in need]), q_centre, checker)
    for (name, d, _), why in zip(need, r.why, strict=True):
        if why is not None:
            return None, f"{name}{' approach from ' + d if d else ''}: {why}"
    poses: dict[str, np.ndarray] = {}
    approach: dict[str, dict[str, np.ndarray]] = {}
    for (name, d, _), q in zip(need, r.q, strict=True):
        if name.startswith("grid"):
            continue
        if d is None:
            poses[name] = q
        else:
            approach.setdefault(name, {})[d] = q
    for name, by_dir in approach.items():
        for d, qa in by_dir.items():
            by_dir[d] = preloaded(model, poses[name], qa)
    return Plan(cube, poses, approach), None


def preloaded(model, q: np.ndarray, q_approach: np.ndarray) -> np.ndarray:
    """The approach configuration with every joint at least ``PRELOAD`` from the pose, on the side the approach
    direction turns it from (a joint it does not turn: from below). The last motion then takes up each joint's
    backlash on a side fixed by the pose and the direction alone, whatever the arm did before (a joint that did
    not move would keep the side of an earlier, different motion)."""
    least = np.array([PRELOAD if j.revolute else PRELOAD_LENGTH for j in model.joints])
    delta = np.asarray(q, float) - np.asarray(q_approach, float)
    side = np.where(np.abs(delta) > 1e-9, np.sign(delta), 1.0)
    return np.asarray(q, float) - side * np.maximum(np.abs(delta), least)


def largest_cube(model, q_start, directions: dict[str, tuple[str, ...]], *, plane: str = "x+", checker=None,
                 centre=None, max_edge: float = 2.0, min_edge: float = 0.02, iterations: int = 14) -> Plan:
    """The test cube of the largest edge (bisection, to ``max_edge / 2^iterations``) centred at ``centre``
    (default: the tool's position at ``q_start``) with the tool's orientation at ``q_start``."""
    q_start = np.asarray(q_start, float)
    T0 = model.fk(q_start[None])[0]
    c = T0[:3, 3] if centre is None else np.asarray(centre, float)
    _plane_corners(plane)
    centre_pose = np.eye(4)
    centre_pose[:3, :3], centre_pose[:3, 3] = T0[:3, :3], c
    r = reach(model, centre_pose[None], q_start, checker)
    if not r.ok:
        raise CubeError(f"test cube: its centre ({', '.join(f'{v * 1e3:.1f}' for v in c)} mm) is not usable: "
                        f"{r.why[0]}; jog the tool to the middle of the area of greatest use")
    q_c = r.q[0]
    lo, hi, best, why_hi = 0.0, float(max_edge), None, None
    plan, why = plan_cube(model, TestCube(c, hi, T0[:3, :3], plane), q_c, directions, checker)
    if plan is not None:
        return plan
    for _ in range(iterations):
        mid = (lo + hi) / 2
        plan, why = plan_cube(model, TestCube(c, mid, T0[:3, :3], plane), q_c, directions, checker)
        if plan is not None:
            lo, best = mid, plan
        else:
            hi, why_hi = mid, why
    if best is None or best.cube.edge < min_edge:
        raise CubeError(f"test cube: no cube of {min_edge * 1e3:.0f} mm fits around the tool "
                        f"({why_hi or why}); jog the tool away from the limits, or give --cube")
    best.cube.notes.append(f"edge limited by: {why_hi}")
    return best


def given_cube(model, q_start, directions: dict[str, tuple[str, ...]], centre, edge: float, *, plane: str = "x+",
               checker=None, rotation=None) -> Plan:
    """The cube the user gave (centre, edge), with the tool's orientation at ``q_start`` unless ``rotation``;
    ``CubeError`` naming the first pose that is not usable."""
    q_start = np.asarray(q_start, float)
    T0 = model.fk(q_start[None])[0]
    R = T0[:3, :3] if rotation is None else np.asarray(rotation, float)
    c = np.asarray(centre, float)
    centre_pose = np.eye(4)
    centre_pose[:3, :3], centre_pose[:3, 3] = R, c
    r = reach(model, centre_pose[None], q_start, checker)
    if not r.ok:
        raise CubeError(f"test cube: its centre is not usable: {r.why[0]}")
    plan, why = plan_cube(model, TestCube(c, float(edge), R, plane), r.q[0], directions, checker)
    if plan is None:
        raise CubeError(f"test cube (edge {edge * 1e3:.1f} mm): {why}; give a smaller --cube edge")
    return plan
