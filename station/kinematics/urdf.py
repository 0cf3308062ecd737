"""URDF robots as station models.

A URDF is a tree of links joined by joints, each joint placed by an ``<origin>`` in its parent link and
turning (or sliding) about an ``<axis>``. The station takes the serial chain from a base link to a tip link:
fixed joints are folded into their neighbours, revolute, continuous and prismatic joints become the model's
joints (in order from the base), and the chain is converted to modified DH with Hayati's beta
(``from_mdh``), the station's minimal convention: one parameter per physical error (docs/formats.md says
why). Frame 0 of the model is the base link; ``base.*`` places the first joint's MDH frame in it, ``tcp.*``
places the tip link in the last one. Link masses and centres of mass come from ``<inertial>`` (every link
rigidly attached to a chain body counts, off-chain joints at zero).

``load_urdf(path, tip_link=None, base_link=None)`` -> Model. The conversion is checked against a direct
evaluation of the URDF's joint transforms at a few configurations before the model is returned."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.kinematics import se3
from station.kinematics.chain import forward
from station.kinematics.model import PARALLEL_TOL, Joint, Model, from_mdh
from station.kinematics.modelfile import ModelFileError
from station.kinematics.urdfxml import Node, XMLFileError, read

MOVABLE = ("revolute", "continuous", "prismatic")
KNOWN_TYPES = MOVABLE + ("fixed", "floating", "planar")
CONTINUOUS_LIMIT = 2 * math.pi  # a continuous joint gets +-360 deg: every angle, twice
NO_RANGE_SLIDE = 10.0  # m: the range of a prismatic joint whose <limit> gives none (motion limits come from the cell)
DEFAULT_VELOCITY = 1.0  # rad/s or m/s when <limit velocity> is missing
DEFAULT_ACCELERATION = 10.0  # URDF has no acceleration limit
CHECK_TOL = 1e-9  # m / rad: conversion check against the URDF's own transforms
# Physical bounds of the numbers a URDF may hold. Beyond them a value is a typo or a unit slip, and letting it
# through ends in overflow or an internal error far from the file: the element is named instead.
MAX_LENGTH = 1000.0  # m: an <origin xyz> or limit of a robot (a kilometre is no robot)
MAX_ANGLE = 1000.0  # rad: an <origin rpy> angle or a revolute limit (~160 turns)
MAX_AXIS = 1e6  # an <axis xyz> component (a direction; it is normalised)
MIN_AXIS = 1e-9  # below this norm the axis has no direction
MAX_MASS = 1e6  # kg of one link
MAX_REACH = 20.0  # m: a chain longer than this is not an arm in metres (millimetres in a metre file?)


@dataclass
class UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # 4x4, in the parent link
    axis: np.ndarray  # unit, in the joint (= child) frame
    lower: float
    upper: float
    velocity: float
    calibration: dict[str, float]
    mimic: str | None
    node: Node

    @property
    def movable(self) -> bool:
        return self.type in MOVABLE


@dataclass
class UrdfLink:
    name: str
    mass: float
    com: np.ndarray  # in the link frame
    node: Node


@dataclass
class UrdfRobot:
    name: str
    path: str
    root: Node  # the document, for export
    links: dict[str, UrdfLink]
    joints: dict[str, UrdfJoint]
    parent_of: dict[str, str] = field(default_factory=dict)  # child link -> joint name
    # accepted as urdfdom does, but worth a word: (joint name, one line); a chain reports those of its joints
    warnings: list[tuple[str, str]] = field(default_factory=list)

    def warn(self, joint: str, node: Node | None, msg: str) -> None:
        self.warnings.append((joint, f"{self.path}:{node.line}: {msg}" if node is not None else f"{self.path}: {msg}"))

    def fail(self, node: Node | None, msg: str) -> ModelFileError:
        return ModelFileError(f"{self.path}:{node.line}: {msg}" if node is not None else f"{self.path}: {msg}")

    def children_of(self, link: str) -> list[UrdfJoint]:
        return [j for j in self.joints.values() if j.parent == link]

    def path_to(self, link: str) -> list[UrdfJoint]:
        """Joints from the root of ``link``'s tree down to ``link``."""
        out: list[UrdfJoint] = []
        seen = {link}
        while link in self.parent_of:
            j = self.joints[self.parent_of[link]]
            if j.parent in seen:
                raise self.fail(j.node, f"closed loop: joint {j.name!r} leads back to link {j.parent!r}")
            seen.add(j.parent)
            out.append(j)
            link = j.parent
        return out[::-1]


# ---- reading ------------------------------------------------------------------------------------
def _floats(robot_path: str, node: Node, attr: str, n: int, default: list[float], bound: float | None = None,
            what: str = "") -> list[float]:
    """``n`` finite numbers of ``node``'s attribute ``attr`` (``default`` when absent), each within ``bound``."""
    text = node.attrib.get(attr)
    if text is None:
        return list(default)
    try:
        vals = [float(x) for x in text.split()]
    except ValueError:
        vals = []
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ModelFileError(f"{robot_path}:{node.line}: <{node.tag} {attr}={text!r}>: expected {n} finite numbers")
    if bound is not None and any(abs(v) > bound for v in vals):
        raise ModelFileError(f"{robot_path}:{node.line}: <{node.tag} {attr}={text!r}>: {max(vals, key=abs):g} is "
                             f"beyond the physical bound of {bound:g}{what}")
    return vals


def _origin(path: str, parent: Node) -> np.ndarray:
    o = parent.first("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(path, o, "xyz", 3, [0, 0, 0], MAX_LENGTH, " m")
    rpy = _floats(path, o, "rpy", 3, [0, 0, 0], MAX_ANGLE, " rad")
    return se3.pose_to_matrix(np.array(xyz + rpy), "rpy")


def _attr_float(path: str, node: Node, attr: str, default: float | None, bound: float | None = None,
                what: str = "") -> float | None:
    if attr not in node.attrib:
        return default
    return _floats(path, node, attr, 1, [], bound, what)[0]


def _limits(robot: UrdfRobot, jn: Node, name: str, jtype: str) -> tuple[float, float, float]:
    """(lower, upper, velocity) of a joint, as urdfdom reads them: a ``<limit>`` counts only on a revolute or
    prismatic joint (continuous, fixed, floating and planar joints ignore it, whatever it says). A moving joint
    without a usable range or speed is accepted with a warning: the station's own motion limits come from the
    cell and limits files, and a URDF's limits bind motion only, never the readings."""
    path = robot.path
    lim = jn.first("limit")
    velocity = DEFAULT_VELOCITY
    if jtype == "continuous" or jtype not in MOVABLE:
        if jtype == "continuous" and lim is not None and "velocity" in lim.attrib:
            v = _attr_float(path, lim, "velocity", DEFAULT_VELOCITY)
            velocity = v if v > 0 else DEFAULT_VELOCITY
        return -CONTINUOUS_LIMIT, CONTINUOUS_LIMIT, velocity
    rev = jtype == "revolute"
    bound, unit = (MAX_ANGLE, " rad") if rev else (MAX_LENGTH, " m")
    wide = CONTINUOUS_LIMIT if rev else NO_RANGE_SLIDE
    if lim is None:
        robot.warn(name, jn, f"joint {name!r}: a {jtype} joint without <limit>: taken as unlimited "
                       f"(+-{wide:g} {unit.strip()}); motion limits come from the station's limits")
        return -wide, wide, velocity
    lower = _attr_float(path, lim, "lower", 0.0)
    upper = _attr_float(path, lim, "upper", 0.0)
    velocity = _attr_float(path, lim, "velocity", DEFAULT_VELOCITY)
    if max(abs(lower), abs(upper)) > bound:  # simulators write +-1e16 for "no limit"
        robot.warn(name, lim, f"joint {name!r}: <limit lower={lower:g} upper={upper:g}> is beyond any physical range: "
                              f"taken as unlimited (+-{wide:g} {unit.strip()}); motion limits come from the station's "
                              f"limits")
        lower, upper = -wide, wide
    sc = jn.first("safety_controller")
    if sc is not None:  # the controller's soft limits are tighter, where they leave a range
        slo = max(lower, _attr_float(path, sc, "soft_lower_limit", lower))
        shi = min(upper, _attr_float(path, sc, "soft_upper_limit", upper))
        if slo < shi:
            lower, upper = slo, shi
    if not lower < upper:
        robot.warn(name, lim, f"joint {name!r}: <limit lower={lower:g} upper={upper:g}> gives the joint no range: "
                              f"taken as unlimited (+-{wide:g} {unit.strip()}); motion limits come from the station's "
                              f"limits")
        lower, upper = -wide, wide
    if not velocity > 0:
        robot.warn(name, lim, f"joint {name!r}: <limit velocity={velocity:g}> on a joint that moves: taken as "
                        f"{DEFAULT_VELOCITY:g}{unit}/s; motion speeds come from the station's limits")
        velocity = DEFAULT_VELOCITY
    return lower, upper, velocity


def _axis(robot: UrdfRobot, jn: Node, name: str, jtype: str) -> np.ndarray:
    an = jn.first("axis")
    if an is None:
        return np.array([1.0, 0.0, 0.0])  # urdfdom's default
    axis = np.array(_floats(robot.path, an, "xyz", 3, [1, 0, 0], MAX_AXIS, " (a direction)"))
    norm = float(np.linalg.norm(axis))
    if jtype in MOVABLE:
        if norm < MIN_AXIS:
            raise robot.fail(an, f"joint {name!r}: zero axis")
        return axis / norm
    return axis / norm if norm >= MIN_AXIS else np.array([1.0, 0.0, 0.0])  # unused: the joint does not move


def _read_link(robot: UrdfRobot, ln: Node) -> UrdfLink:
    """A ``<link>``: its name (unique) and mass with its centre (the inertia tensor does not matter here)."""
    name = ln.attrib.get("name")
    if not name:
        raise robot.fail(ln, "<link> without a name")
    if name in robot.links:
        raise robot.fail(ln, f"link {name!r} is defined twice (first on line {robot.links[name].node.line})")
    mass, com = 0.0, np.zeros(3)
    inertial = ln.first("inertial")
    if inertial is not None:
        mn = inertial.first("mass")
        if mn is not None:
            mass = _attr_float(robot.path, mn, "value", 0.0, MAX_MASS, " kg")
            if mass < 0:
                raise robot.fail(mn, f"link {name!r}: negative mass {mass}")
        com = _origin(robot.path, inertial)[:3, 3]  # the inertia tensor's orientation does not matter here
    return UrdfLink(name, mass, com, ln)


def _joint_ends(robot: UrdfRobot, jn: Node, name: str) -> dict[str, str]:
    """``{"parent": link, "child": link}``, both defined links."""
    ends = {}
    for end in ("parent", "child"):
        e = jn.first(end)
        link = None if e is None else e.attrib.get("link")
        if link is None:
            raise robot.fail(jn, f"joint {name!r}: missing <{end} link=...>")
        if link not in robot.links:
            raise robot.fail(e, f"joint {name!r}: {end} link {link!r} is not defined")
        ends[end] = link
    return ends


def _read_joint(robot: UrdfRobot, jn: Node) -> UrdfJoint:
    """A ``<joint>``: name (unique), type, ends, origin, axis, limits, calibration marks, mimic."""
    name = jn.attrib.get("name")
    jtype = jn.attrib.get("type")
    if not name:
        raise robot.fail(jn, "<joint> without a name")
    if name in robot.joints:
        raise robot.fail(jn, f"joint {name!r} is defined twice (first on line {robot.joints[name].node.line})")
    if jtype not in KNOWN_TYPES:
        raise robot.fail(jn, f"joint {name!r}: type {jtype!r} is not one of {', '.join(KNOWN_TYPES)}")
    ends = _joint_ends(robot, jn, name)
    axis = _axis(robot, jn, name, jtype)
    lower, upper, velocity = _limits(robot, jn, name, jtype)
    cal = jn.first("calibration")
    calibration = {}
    if cal is not None:
        for key in ("rising", "falling", "reference_position"):
            v = _attr_float(robot.path, cal, key, None, MAX_ANGLE if jtype != "prismatic" else MAX_LENGTH)
            if v is not None:
                calibration[key] = v
    mimic = jn.first("mimic")
    return UrdfJoint(name, jtype, ends["parent"], ends["child"], _origin(robot.path, jn), axis, lower, upper,
                     velocity, calibration, None if mimic is None else mimic.attrib.get("joint", "?"), jn)


def _check_tree(robot: UrdfRobot, root: Node) -> None:
    """Something moves, and there is a root link (a link no joint has as its child)."""
    if not robot.joints:
        names = list(robot.links)
        shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
        raise robot.fail(root, f"robot {robot.name!r} has {len(names)} link(s) ({shown}) and no joint: nothing "
                               f"moves, so there is no chain to calibrate (a chain needs a revolute, continuous or "
                               f"prismatic joint)" if names else f"robot {robot.name!r} has no link and no joint")
    if not any(ln not in robot.parent_of for ln in robot.links):
        j = next(iter(robot.joints.values()))
        raise robot.fail(j.node, "closed loop: every link has a parent joint, so there is no root link")


def parse_urdf(root: Node, path: str) -> UrdfRobot:
    if root.tag != "robot":
        raise ModelFileError(f"{path}:{root.line}: <{root.tag}>: a URDF's root element is <robot>")
    robot = UrdfRobot(root.attrib.get("name", Path(path).stem), path, root, {}, {})
    for ln in root.elements("link"):
        link = _read_link(robot, ln)
        robot.links[link.name] = link
    for jn in root.elements("joint"):
        joint = _read_joint(robot, jn)
        robot.joints[joint.name] = joint
        if joint.child in robot.parent_of:  # a link is the child of one joint only: a URDF is a tree
            other = robot.joints[robot.parent_of[joint.child]]
            raise robot.fail(jn, f"closed loop: link {joint.child!r} is the child of joints {other.name!r} "
                                 f"(line {other.node.line}) and {joint.name!r}; a URDF must be a tree")
        robot.parent_of[joint.child] = joint.name
    _check_tree(robot, root)
    return robot


def read_urdf(path: str | Path) -> UrdfRobot:
    try:
        root = read(path)
    except XMLFileError as e:
        raise ModelFileError(str(e)) from None
    return parse_urdf(root, str(path))


# ---- the chain ----------------------------------------------------------------------------------
@dataclass
class UrdfChain:
    """The serial chain base_link -> tip_link of a URDF robot."""

    robot: UrdfRobot
    base: str
    tip: str
    path: list[UrdfJoint]  # every joint from base to tip, fixed ones included
    warnings: list[str] = field(default_factory=list)  # one line each, about the chain's joints

    @property
    def movable(self) -> list[UrdfJoint]:
        return [j for j in self.path if j.movable]

    def fk(self, q: np.ndarray) -> np.ndarray:
        """Tip pose (4x4) in the base link at joint values ``q`` (n,), straight from the URDF transforms."""
        T = np.eye(4)
        i = 0
        for j in self.path:
            T = T @ j.origin
            if j.movable:
                T = T @ _joint_motion(j, q[i])
                i += 1
        return T


def _joint_motion(j: UrdfJoint, value: float) -> np.ndarray:
    M = np.eye(4)
    if j.type == "prismatic":
        M[:3, 3] = j.axis * value
    else:
        M[:3, :3] = se3.rotvec_to_matrix(j.axis * value)
    return M


def _n_movable(robot: UrdfRobot, link: str) -> int:
    return sum(j.movable for j in robot.path_to(link))


def chain_ends(robot: UrdfRobot) -> list[tuple[str, int]]:
    """Every leaf link with a movable joint on its path from the root, with that number, most joints first."""
    leaves = [ln for ln in robot.links if not robot.children_of(ln)]
    depth = [(ln, _n_movable(robot, ln)) for ln in leaves]
    return sorted(((ln, d) for ln, d in depth if d > 0), key=lambda t: (-t[1], t[0]))


def _ends_text(ends: list[tuple[str, int]], limit: int = 12) -> str:
    shown = ", ".join(f"{ln} ({d} joint{'s' if d != 1 else ''})" for ln, d in ends[:limit])
    return shown + (f" and {len(ends) - limit} more" if len(ends) > limit else "")


def chain(robot: UrdfRobot, tip_link: str | None = None, base_link: str | None = None) -> UrdfChain:
    """The chain to ``tip_link`` (default: the end of the only longest chain) from ``base_link`` (default:
    the root of the tip's tree). Refuses what a calibrated serial chain cannot be: a floating or planar joint on
    the chain (several unmeasured degrees of freedom), a chain without a movable joint. A mimic joint on the
    chain is taken as a joint of its own (its reading is a column of the samples, as a joint state lists it)."""
    for given, what in ((tip_link, "tip"), (base_link, "base")):
        if given is not None and given not in robot.links:
            near = ", ".join(sorted(robot.links)[:12])
            raise robot.fail(None, f"no link {given!r} for the {what} link (links: {near}"
                                   f"{', ...' if len(robot.links) > 12 else ''})")
    if tip_link is None:
        ends = chain_ends(robot)
        if not ends:
            kinds = ", ".join(sorted({j.type for j in robot.joints.values()}))
            raise robot.fail(None, f"no movable joint (revolute, continuous, prismatic) in the robot "
                                   f"({len(robot.joints)} joints: {kinds})")
        best = [e for e in ends if e[1] == ends[0][1]]
        if len(best) > 1:
            raise robot.fail(None, f"several chain ends: {_ends_text(ends)}; choose one with --tip-link "
                                   f"(tip_link=) NAME")
        tip_link = best[0][0]
    full = robot.path_to(tip_link)
    if base_link is not None and base_link != tip_link:
        names = [j.parent for j in full]
        if base_link not in names:
            on = " -> ".join([full[0].parent] + [j.child for j in full]) if full else tip_link
            raise robot.fail(None, f"base link {base_link!r} is not on the path to tip link {tip_link!r} ({on})")
        full = full[names.index(base_link):]
    base = full[0].parent if full else tip_link
    for j in full:
        if j.type in ("floating", "planar"):
            raise robot.fail(j.node, f"joint {j.name!r}: a {j.type} joint cannot be part of a calibrated chain "
                                     f"(its {6 if j.type == 'floating' else 3} degrees of freedom have no reading); "
                                     f"start the chain after it with --base-link {j.child}")
    ch = UrdfChain(robot, base, tip_link, full)
    if not ch.movable:
        raise robot.fail(None, f"no movable joint between {base!r} and {tip_link!r}")
    on = {j.name for j in full}
    ch.warnings = [w for jn, w in robot.warnings if jn in on]
    for j in ch.movable:
        if j.mimic is not None:
            ch.warnings.append(f"{robot.path}:{j.node.line}: joint {j.name!r} mimics {j.mimic!r}: on the chain it is a "
                               f"joint of its own (its reading is a column of the samples)")
    return ch


# ---- conversion to modified DH ------------------------------------------------------------------
def _rz(t: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = se3.rot_z(t)
    return T


def _rx(t: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = se3.rot_x(t)
    return T


def _ry(t: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = se3.rot_y(t)
    return T


def _tr(axis: int, v: float) -> np.ndarray:
    T = np.eye(4)
    T[axis, 3] = v
    return T


def _angle_about(a: np.ndarray, b: np.ndarray, z: np.ndarray) -> float:
    """Angle turning unit vector ``a`` into ``b`` about ``z`` (both perpendicular to z)."""
    return math.atan2(float(np.cross(a, b) @ z), float(a @ b))


def mdh_table(lines: list[tuple[np.ndarray, np.ndarray]], tip: np.ndarray) -> tuple[list[dict], dict, dict]:
    """MDH links (``alpha, a, beta, theta, d``), base and tool frames (``x..rz``) of a chain whose joint axes
    at q = 0 are the lines ``(point, unit direction)`` in the base frame and whose tip pose is ``tip``.

    Frame k-1 sits on axis k-1 with x along the common normal to axis k (Craig). A virtual axis 0 (the
    base z axis) places frame 0, whose offset from the base becomes ``base.z`` and ``base.rz``. For
    near-parallel consecutive axes (within ``PARALLEL_TOL``) the common normal is ill-defined: x points
    from frame k-1's origin to where axis k crosses the plane normal to axis k-1, and the small tilt is
    Hayati's beta."""
    pre = np.eye(4)  # frame on axis k-1 before its own Rz(theta) Tz(d)
    links: list[dict] = [{} for _ in lines]
    base: dict = {}
    sin_tol = math.sin(PARALLEL_TOL)
    for k, (pn, zn) in enumerate(lines):
        z, O, xr = pre[:3, 2], pre[:3, 3], pre[:3, 0]
        c = np.cross(z, zn)
        parallel = np.linalg.norm(c) <= sin_tol
        if not parallel:  # common normal
            w0 = O - pn
            b, d_, e_ = float(z @ zn), float(z @ w0), float(zn @ w0)
            d = (b * e_ - d_) / (1 - b * b)
            # its direction is z x zn (well conditioned: the axes are not parallel), its length the offset of the
            # two lines along it; the difference of the two feet would lose every digit of a tiny offset
            ch = c / np.linalg.norm(c)
            a = float((pn - O) @ ch)
            if abs(a) > 1e-12:
                x, a = (ch, a) if a > 0 else (-ch, -a)
            else:  # intersecting axes: either normal direction; keep the one closer to the previous x
                x, a = (ch if ch @ xr >= 0 else -ch), 0.0
        else:  # (near) parallel: Hayati
            d = 0.0
            v = pn - float((pn - O) @ z) / float(zn @ z) * zn - O
            a = float(np.linalg.norm(v))
            x, a = (v / a, a) if a > 1e-12 else (xr, 0.0)
        theta = _angle_about(xr, x, z)
        M = pre @ _rz(theta) @ _tr(2, d)  # frame k-1
        y = np.cross(M[:3, 2], M[:3, 0])
        beta = math.asin(max(-1.0, min(1.0, float(zn @ M[:3, 0])))) if parallel else 0.0
        alpha = math.atan2(-float(zn @ y), float(zn @ M[:3, 2]))
        if k == 0:
            base = {"z": d, "rz": theta}
        else:
            links[k - 1].update(theta=theta, d=d)
        links[k].update(alpha=alpha, a=a, beta=beta)
        pre = M @ _rx(alpha) @ _tr(0, a) @ _ry(beta)
    # last frame: on the last axis level with the tip, x unchanged
    d_last = float((tip[:3, 3] - pre[:3, 3]) @ pre[:3, 2])
    links[-1].update(theta=0.0, d=d_last)
    M = pre @ _tr(2, d_last)
    tool_T = se3.invert(M) @ tip
    rx, ry, rz = se3.matrix_to_rpy(tool_T[:3, :3])
    tool = dict(x=tool_T[0, 3], y=tool_T[1, 3], z=tool_T[2, 3], rx=rx, ry=ry, rz=rz)
    return links, {"x": 0.0, "y": 0.0, "rx": 0.0, "ry": 0.0, **base}, tool


def _link_poses(robot: UrdfRobot, base: str) -> dict[str, np.ndarray]:
    """Pose at q = 0 of every link below ``base`` (every joint at zero), in the base link frame."""
    poses = {base: np.eye(4)}
    todo = [base]
    while todo:
        ln = todo.pop()
        for j in robot.children_of(ln):
            if j.child not in poses:
                poses[j.child] = poses[ln] @ j.origin
                todo.append(j.child)
    return poses


def model_from_chain(ch: UrdfChain) -> Model:
    robot = ch.robot
    mov = ch.movable
    n = len(mov)
    # joint frames and tip at q = 0 in the base link
    T = np.eye(4)
    lines = []
    body_of: dict[str, int] = {ch.base: 0}  # chain link -> body index (number of movable joints before it)
    k = 0
    for j in ch.path:
        T = T @ j.origin
        if j.movable:
            lines.append((T[:3, 3].copy(), T[:3, :3] @ j.axis))
            k += 1
        body_of[j.child] = k
    _check_reach(ch)
    links, base, tool = mdh_table(lines, T)
    joints = []
    for j in mov:
        kind = "prismatic" if j.type == "prismatic" else "revolute"
        joints.append(Joint(j.name, kind, j.lower, j.upper, j.velocity, DEFAULT_ACCELERATION))
    # masses: every link hangs on the chain body of its nearest ancestor on the chain
    poses = _link_poses(robot, ch.base)
    world_masses: list[tuple[int, float, np.ndarray]] = []
    for name, ln in robot.links.items():
        if ln.mass <= 0 or name not in poses:
            continue
        a = name
        while a not in body_of:
            a = robot.joints[robot.parent_of[a]].parent
        if body_of[a] > 0:
            world_masses.append((body_of[a], ln.mass, poses[name][:3, :3] @ ln.com + poses[name][:3, 3]))
    desc = f"from URDF {Path(robot.path).name}: {ch.base} -> {ch.tip}"
    m = from_mdh(robot.name, joints, links, base=base, tool=tool, description=desc)
    if world_masses:
        _, prefix = forward(m.chain, np.zeros((1, n)), m.params, keep_prefix=True)
        frames = [prefix[0, e + 1] for e in m.frames]  # a link frame is never the chain's last element
        masses: dict[int, list] = {}
        for body, mass, p in world_masses:
            com = se3.invert(frames[body - 1]) @ np.append(p, 1.0)
            masses.setdefault(body, []).append((mass, com[:3]))
        merged = {kk: (sum(mm for mm, _ in v), sum(mm * c for mm, c in v) / sum(mm for mm, _ in v))
                  for kk, v in masses.items()}
        m = m.with_masses(merged)
    # each URDF link frame in its station link frame (fixed: both are attached to the same body), for export
    _, prefix = forward(m.chain, np.zeros((1, n)), m.params, keep_prefix=True)
    poses_k = []
    W = np.eye(4)
    for j in ch.path:
        W = W @ j.origin
        if j.movable:
            poses_k.append(W.copy())
    link_in_frame = [se3.invert(prefix[0, e + 1]) @ Wk for e, Wk in zip(m.frames, poses_k, strict=True)]
    src = {**m.source, "urdf": {"path": robot.path, "base_link": ch.base, "tip_link": ch.tip, "chain": ch,
                                "link_in_frame": link_in_frame,
                                "calibration": {j.name: j.calibration for j in mov if j.calibration}},
           "warnings": list(ch.warnings)}
    from dataclasses import replace

    m = replace(m, source=src)
    _check(ch, m)
    return m


def _check_reach(ch: UrdfChain) -> None:
    """A chain whose links add up to more than ``MAX_REACH`` is not an arm in metres: every URDF length is in
    metres, so such a file was most likely written in millimetres (or scaled by 1000 on the way)."""
    first = next(i for i, j in enumerate(ch.path) if j.movable)
    reach = sum(float(np.linalg.norm(j.origin[:3, 3])) for j in ch.path[first + 1:])
    if reach > MAX_REACH:
        longest = max(ch.path[first + 1:], key=lambda j: float(np.linalg.norm(j.origin[:3, 3])))
        alone = float(np.linalg.norm(longest.origin[:3, 3]))
        raise ch.robot.fail(longest.node, f"the chain {ch.base} -> {ch.tip} reaches {reach:.4g} m (joint "
                                          f"{longest.name!r} alone {alone:.4g} m): no arm is that long; URDF lengths "
                                          f"are metres - were these millimetres?")


def _check(ch: UrdfChain, m: Model) -> None:
    """The converted model against the URDF's own transforms at q = 0 and a few random configurations."""
    rng = np.random.default_rng(0)
    lo = np.maximum(m.lower, -math.pi)
    hi = np.minimum(m.upper, math.pi)
    qs = np.vstack([np.zeros(m.n_joints), lo + (hi - lo) * rng.random((4, m.n_joints))])
    rigid = m.with_params({n: 0.0 for n in m.param_names if n.startswith("compliance.")})
    got = rigid.fk(qs)
    for q, G in zip(qs, got, strict=True):
        W = ch.fk(q)
        err = max(float(np.abs(W[:3, 3] - G[:3, 3]).max()), float(np.abs(W[:3, :3] - G[:3, :3]).max()))
        if not err < CHECK_TOL:
            raise ModelFileError(f"{ch.robot.path}: internal error: the MDH conversion of {ch.base} -> {ch.tip} "
                                 f"is off by {err:.3g} at q = {np.round(q, 4).tolist()} (please report)")


def load_urdf(path: str | Path, tip_link: str | None = None, base_link: str | None = None) -> Model:
    """A URDF file as a station model (see the module doc)."""
    robot = read_urdf(path)
    return model_from_chain(chain(robot, tip_link, base_link))
