"""Link envelopes (capsules) and keep-out volumes: how close every link of the arm comes to the mounting plane,
a fixture or a fence, vectorised over N joint configurations. Pure numpy, SI (m, rad), no I/O.

The arm's body is approximated by capsules along its kinematic chain: every translation of the chain (a DH
``d`` and ``a``, a POE frame's offset) is a segment, owned by the link the preceding joint moves, with that
link's radius; the tool is a capsule from the flange towards the TCP. Two ends are trimmed so the envelope
does not invent material: the last link ends at the flange face (not a radius beyond it), and the tool
envelope stops ``tool_free`` short of the TCP (the tip is meant to touch the references).

An obstacle is a half-space (``Plane``: the allowed side is where ``normal . x >= offset``) or an oriented
box (``Box``). The mounting plane is the half-space the robot stands on; links that cannot change their
distance to it whatever the joints do (the base column of a table arm: it stands on the plane by design)
are not checked against it. Every obstacle has a clearance: a link closer than that is a violation."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from station.kinematics.chain import TZ

DEFAULT_CLEARANCE = 0.01  # m: links keep 10 mm from a keep-out unless the cell says otherwise
PATH_STEP = 0.005  # m: no point of the arm moves more than this between two checked samples of a path


# ---- obstacles ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plane:
    """Half-space keep-out: everything on the side ``normal . x < offset`` is forbidden (``normal`` points
    into the free side, unit, base frame; ``offset`` m)."""

    name: str
    normal: np.ndarray
    offset: float
    clearance: float = DEFAULT_CLEARANCE

    @classmethod
    def through(cls, name: str, point, normal, clearance: float = DEFAULT_CLEARANCE) -> Plane:
        n = np.asarray(normal, float)
        n = n / np.linalg.norm(n)
        return cls(name, n, float(n @ np.asarray(point, float)), float(clearance))

    def to_dict(self) -> dict:
        return {"name": self.name, "plane": {"normal": self.normal.tolist(), "offset": self.offset},
                "clearance": self.clearance}


@dataclass(frozen=True)
class Box:
    """Oriented box keep-out: centre (m), ``rotation`` (3x3, columns = box axes in the base frame), ``half``
    extents along those axes (m). An axis-aligned box has the identity rotation."""

    name: str
    center: np.ndarray
    half: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    clearance: float = DEFAULT_CLEARANCE

    @classmethod
    def from_corners(cls, name: str, lo, hi, clearance: float = DEFAULT_CLEARANCE) -> Box:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return cls(name, (lo + hi) / 2, np.abs(hi - lo) / 2, np.eye(3), float(clearance))

    def to_dict(self) -> dict:
        return {"name": self.name, "box": {"center": self.center.tolist(), "size": (2 * self.half).tolist(),
                                           "rotation": self.rotation.tolist()}, "clearance": self.clearance}


Obstacle = Plane | Box


@dataclass(frozen=True)
class KeepOut:
    """Everything the links must stay clear of: the mounting plane (None: the arm is not standing on a plane
    the station knows, e.g. a wall or ceiling mount described as an ordinary keep-out) and the obstacles."""

    mounting: Plane | None = None
    obstacles: tuple[Obstacle, ...] = ()

    @classmethod
    def default(cls, clearance: float = DEFAULT_CLEARANCE) -> KeepOut:
        """A table-mounted arm: nothing below the plane its base stands on (z = 0 of the base frame)."""
        return cls(Plane("mounting plane", np.array([0.0, 0.0, 1.0]), 0.0, clearance), ())

    @classmethod
    def none(cls) -> KeepOut:
        return cls(None, ())

    @property
    def all(self) -> tuple[Obstacle, ...]:
        return ((self.mounting,) if self.mounting is not None else ()) + tuple(self.obstacles)

    def __bool__(self) -> bool:
        return bool(self.all)

    def to_dict(self) -> dict:
        return {"mounting": None if self.mounting is None else self.mounting.to_dict(),
                "keep_out": [o.to_dict() for o in self.obstacles]}


# ---- the arm's envelope ------------------------------------------------------------------------
@dataclass(frozen=True)
class Envelope:
    """Capsule segments of one model: key points are origins after chain elements ``element`` (-1: the base
    origin); segment s runs from key point ``a[s]`` to ``b[s]`` (end pulled back by ``trim[s]`` m towards
    the start), belongs to ``link[s]`` (1..n the joint that moves it, n+1 the tool) with ``radius[s]``."""

    element: np.ndarray  # (K,) chain element index after which key point k is taken, -1 = robot base origin
    a: np.ndarray  # (S,)
    b: np.ndarray  # (S,)
    link: np.ndarray  # (S,)
    radius: np.ndarray  # (S,)
    trim: np.ndarray  # (S,)
    names: tuple[str, ...]  # (n + 1,) link names "shoulder-elbow" (joint i to joint i+1, the last to "flange"), "tool"
    reach: np.ndarray  # (n,) upper bound of the distance from joint i's axis to any envelope point (m)


def radii_of(model) -> tuple[np.ndarray, float, float]:
    """``(link_radii (n,), tool_radius, tool_free)`` in m: from the model file's ``collision`` section, or a
    default from the arm's size (6 % of its reach, 15..80 mm) when the file has none."""
    c = model.source.get("collision") or {}
    n = model.n_joints
    if "link_radii" in c:
        radii = np.asarray(c["link_radii"], float)
    else:
        reach = _reach_total(model)
        radii = np.full(n, float(np.clip(0.06 * reach, 0.015, 0.08)))
    return radii, float(c.get("tool_radius", 0.01)), float(c.get("tool_free", 0.02))


def _reach_total(model) -> float:
    P = _origins(model, np.zeros((1, model.n_joints)), np.arange(model.chain.n_elements))
    return float(np.sum(np.linalg.norm(np.diff(P[0], axis=0), axis=1)))


def _frame_prefix(name: str) -> str | None:
    """``base.x`` -> ``base``: translations of one fixed frame (x, y, z) are one straight segment."""
    head, _, tail = name.rpartition(".")
    return head if tail in ("x", "y", "z") else None


def envelope(model) -> Envelope:
    ch = model.chain
    names = model.param_names
    n = model.n_joints
    radii, tool_r, tool_free = radii_of(model)
    pname = [names[p] if p >= 0 else "" for p in ch.param]
    # the robot starts after the base frame; the tool after the last joint's block, at the first tcp element
    first_joint = int(np.flatnonzero(ch.joint >= 0)[0])
    tcp_start = next((k for k in range(ch.n_elements) if pname[k].startswith("tcp.")), ch.n_elements)
    keys: list[int] = [first_joint - 1]
    owner: list[int] = []  # owner of the segment ending at key point k (k >= 1)
    link = 0
    for k in range(first_joint, ch.n_elements):
        if ch.joint[k] >= 0:
            link = int(ch.joint[k]) + 1
        if k == tcp_start:
            keys.append(k - 1)  # the flange
            owner.append(link)
            link = n + 1
        if ch.axis[k] > TZ:
            continue
        pre = _frame_prefix(pname[k])
        if pre is not None and k + 1 < ch.n_elements and ch.axis[k + 1] <= TZ and _frame_prefix(pname[k + 1]) == pre:
            continue  # same fixed frame continues: one straight segment
        keys.append(k)
        owner.append(link)
    if tcp_start == ch.n_elements:  # no tool frame in the chain
        keys.append(ch.n_elements - 1)
        owner.append(link)
    keys_a = np.array(keys)
    a, b, own = np.arange(len(keys) - 1), np.arange(1, len(keys)), np.array(owner)
    # segment lengths over the joint range (a prismatic joint's segment changes length): drop what is not there
    # (a zero DH a or d: a point, covered by the neighbouring capsules' caps)
    P = _origins(model, _spread(model), keys_a)
    longest = np.max(np.linalg.norm(P[:, b] - P[:, a], axis=2), axis=0)
    keep = longest > 1e-3
    a, b, own, longest = a[keep], b[keep], own[keep], longest[keep]
    r = np.where(own <= n, radii[np.clip(own - 1, 0, n - 1)], tool_r)
    trim = np.zeros(len(a))
    arm = np.flatnonzero(own <= n)
    if arm.size:
        trim[arm[-1]] = r[arm[-1]]  # the last link ends at the flange face
    trim[own == n + 1] = tool_r + tool_free  # the tool envelope stops tool_free short of the TCP
    # distance bound from joint i's axis to anything it moves: the chain length after it plus the largest radius
    reach = np.array([longest[own >= i + 1].sum() + (r.max() if r.size else 0.0) for i in range(n)])
    ends = [j.name for j in model.joints] + ["flange"]
    names = tuple(f"{ends[i]}-{ends[i + 1]}" for i in range(n)) + ("tool",)
    return Envelope(keys_a, a, b, own, r, trim, names, reach)


def _spread(model, n: int = 16) -> np.ndarray:
    """Fixed, spread-out configurations inside the joint limits (zero, lower and upper limits first)."""
    lo, hi = np.maximum(model.lower, -np.pi), np.minimum(model.upper, np.pi)
    Q = lo + (hi - lo) * np.random.default_rng(0).random((n, model.n_joints))
    Q[0] = np.clip(0.0, model.lower, model.upper)
    Q[1], Q[2] = model.lower, model.upper
    return Q


def _element_matrix(axis: int, v: float) -> np.ndarray:
    E = np.eye(4)
    if axis <= TZ:
        E[axis, 3] = v
        return E
    c, s_ = np.cos(v), np.sin(v)
    i, j = {3: (1, 2), 4: (2, 0), 5: (0, 1)}[axis]
    E[i, i], E[i, j], E[j, i], E[j, j] = c, -s_, s_, c
    return E


def _compile(model, elements: np.ndarray, params) -> list[tuple]:
    """The chain folded for key-point FK: runs of fixed elements become one constant transform (the model's
    parameters are fixed during a check), with the key points inside a run as constant offsets."""
    ch = model.chain
    v = ch.const + np.where(ch.param >= 0, params[np.maximum(ch.param, 0)], 0.0)
    want: dict[int, list[int]] = {}  # element -> every slot that asks for it (two capsules may share an end)
    for i, e in enumerate(elements):
        want.setdefault(int(e), []).append(i)
    ops: list[tuple] = []
    acc = np.eye(4)
    pending: list[tuple[int, np.ndarray]] = []  # (slot, offset in the frame where the run started)
    last = int(max(elements)) if len(elements) else -1

    def flush():
        nonlocal acc, pending
        if pending or not np.allclose(acc, np.eye(4)):
            ops.append(("const", acc.copy(), [(sl, off.copy()) for sl, off in pending]))
        acc, pending = np.eye(4), []

    for slot in want.get(-1, ()):
        pending.append((slot, np.zeros(3)))
    for k in range(last + 1):
        if ch.joint[k] >= 0:
            flush()
            ops.append(("joint", int(ch.axis[k]), int(ch.joint[k]), float(v[k])))
        else:
            acc = acc @ _element_matrix(int(ch.axis[k]), float(v[k]))
        if k in want:
            if ch.joint[k] >= 0:
                ops.append(("const", np.eye(4), [(slot, np.zeros(3)) for slot in want[k]]))
            else:
                pending.extend((slot, acc[:3, 3].copy()) for slot in want[k])
    flush()
    return ops


def _origins(model, Q: np.ndarray, elements: np.ndarray, params=None, ops: list | None = None) -> np.ndarray:
    """Origins ``(N, K, 3)`` of the frames after each chain element in ``elements`` (-1: before the first)."""
    p = model.params if params is None else np.asarray(params, float)
    ops = ops if ops is not None else _compile(model, elements, p)
    Q = np.atleast_2d(np.asarray(Q, float))
    N = Q.shape[0]
    R = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    t = np.zeros((N, 3))
    out = np.full((N, len(elements), 3), np.nan)  # every slot is written below; NaN would show one that is not
    for op in ops:
        if op[0] == "joint":
            _, axis, j, c = op
            x = Q[:, j] + c
            if axis <= TZ:
                t += x[:, None] * R[:, :, axis]
            else:
                cs, sn = np.cos(x)[:, None], np.sin(x)[:, None]
                i, k = {3: (1, 2), 4: (2, 0), 5: (0, 1)}[axis]
                ci, ck = R[:, :, i].copy(), R[:, :, k]
                R[:, :, i] = cs * ci + sn * ck
                R[:, :, k] = -sn * ci + cs * ck
        else:
            _, C, keys = op
            for slot, off in keys:
                out[:, slot] = t + R @ off
            t = t + R @ C[:3, 3]
            R = R @ C[:3, :3]
    return out


def capsules(model, Q, env: Envelope | None = None, params=None,
             ops: list | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Capsule axes ``A, B (N, S, 3)`` (m, base frame) and radii ``(S,)`` at configurations ``Q (N, n)``
    (``ops``: the chain compiled for ``env`` and these parameters, see ``_compile``)."""
    env = env or envelope(model)
    P = _origins(model, Q, env.element, params, ops)
    A, B = P[:, env.a], P[:, env.b]
    if np.any(env.trim > 0):
        d = B - A
        L = np.linalg.norm(d, axis=2, keepdims=True)
        cut = np.minimum(env.trim[None, :, None], L)  # a segment shorter than its trim shrinks to its start
        B = B - d * np.divide(cut, L, out=np.zeros_like(L), where=L > 1e-12)
    return A, B, env.radius


# ---- distances ---------------------------------------------------------------------------------
def _plane_distance(A, B, plane: Plane) -> np.ndarray:
    """Signed distance of segments to the free side's boundary (negative: some part is beyond the plane)."""
    return np.minimum(A @ plane.normal, B @ plane.normal) - plane.offset


def _box_sdf(P, box: Box) -> np.ndarray:
    """Signed distance of points ``(..., 3)`` to a box (negative inside)."""
    local = np.abs((P - box.center) @ box.rotation) - box.half
    outside = np.linalg.norm(np.maximum(local, 0.0), axis=-1)
    inside = np.minimum(np.max(local, axis=-1), 0.0)
    return outside + inside


def _box_distance(A, B, box: Box, iters: int = 22) -> np.ndarray:
    """Signed distance of segments to a box: the signed distance of a convex set is convex along a line, so a
    golden-section search over the segment parameter finds its minimum; what the search leaves open (~3e-5 of
    the segment length) is subtracted, so the result never overstates the distance."""
    g = (np.sqrt(5.0) - 1) / 2
    d = B - A

    def f(t):
        return _box_sdf(A + d * t[..., None], box)

    lo, hi = np.zeros(A.shape[:-1]), np.ones(A.shape[:-1])
    c, e = hi - g, lo + g
    fc, fe = f(c), f(e)
    for _ in range(iters):
        left = fc < fe  # the minimum lies in [lo, e]
        hi = np.where(left, e, hi)
        lo = np.where(left, lo, c)
        x = np.where(left, hi - g * (hi - lo), lo + g * (hi - lo))  # the one new point of each search
        fx = f(x)
        c, e, fc, fe = (np.where(left, x, e), np.where(left, c, x),
                        np.where(left, fx, fe), np.where(left, fc, fx))
    # the minimum lies in [lo, hi]; the distance changes no faster than the point moves: a lower bound
    best = np.minimum.reduce([f(np.zeros_like(lo)), f(np.ones_like(lo)), fc, fe])
    return best - (hi - lo) * np.linalg.norm(d, axis=-1)


def _with_tip(model, env: Envelope) -> Envelope:
    """``env`` plus one segment: the tool's again, to the TCP (untrimmed), radius the tool's, link n + 2
    ("tool tip")."""
    tool = np.flatnonzero(env.link == model.n_joints + 1)
    if not tool.size:
        return env
    s = int(tool[-1])

    def plus(x, v):
        return np.append(x, v)

    return replace(env, a=plus(env.a, env.a[s]), b=plus(env.b, env.b[s]), link=plus(env.link, model.n_joints + 2),
                   radius=plus(env.radius, env.radius[s]), trim=plus(env.trim, 0.0), names=(*env.names, "tool tip"))


def _fixed_to_plane(model, env: Envelope, plane: Plane) -> np.ndarray:
    """Per segment: its distance to the plane is the same in every configuration (it stands on the plane by
    design, e.g. the base column), so checking it would only re-discover how the robot is built."""
    A, B, _ = capsules(model, _spread(model), env)
    da, db = A @ plane.normal, B @ plane.normal
    return (np.ptp(da, axis=0) < 1e-9) & (np.ptp(db, axis=0) < 1e-9)


@dataclass(frozen=True)
class Hit:
    """The worst violation of one configuration: ``link`` (1..n, n+1 = tool), its name, the obstacle, and the
    envelope's signed distance to it (m; negative = inside) against the obstacle's clearance."""

    link: int
    link_name: str
    obstacle: str
    distance: float
    clearance: float

    def describe(self) -> str:
        what = self.link_name if self.link_name in ("tool", "tool tip") else f"link {self.link} ({self.link_name})"
        if self.distance < 0:
            return (f"{what} would be {-self.distance * 1e3:.0f} mm inside obstacle '{self.obstacle}' "
                    f"(clearance {self.clearance * 1e3:.0f} mm)")
        return (f"{what} would come within {self.distance * 1e3:.0f} mm of obstacle '{self.obstacle}' "
                f"(clearance {self.clearance * 1e3:.0f} mm)")


class Checker:
    """Precomputed envelope and checked (segment, obstacle) pairs for one model and keep-out; call it on
    configurations. Build once per plan, not per pose."""

    def __init__(self, model, keep_out: KeepOut | None, slack: float = 0.0, tip: bool = False,
                 tip_only: tuple[Obstacle, ...] = ()) -> None:
        """``slack`` (m): accept this much less than each obstacle's clearance (a check at run time of poses
        planned with the full clearance: encoder noise and seating must not make a planned move fail).

        ``tip``: also keep the tool's free end (the ``tool_free`` metres the envelope leaves out so that the tip
        can touch the references) out of every obstacle, without clearance: the check of a move between poses.
        Only the approach to a reference may bring the tip to a surface; a transit that drags it through the
        table is what a real arm's collision reflex stops. ``tip_only``: obstacles only the tip is kept out of
        (the bodies of the references themselves, which the links may pass near)."""
        self.model = model
        self.keep_out = KeepOut.default() if keep_out is None else keep_out
        self.slack = slack
        plain = envelope(model)
        self.env = _with_tip(model, plain) if tip else plain
        tip = len(self.env.a) > len(plain.a)  # an arm without a tool frame has no tip to keep out
        self._ops = _compile(model, self.env.element, model.params)
        tip_only = tuple(tip_only) if tip else ()
        self.obstacles = (*self.keep_out.all, *tip_only)
        S = len(self.env.a)
        self.mask = np.ones((S, len(self.obstacles)), bool)
        if self.keep_out.mounting is not None:
            self.mask[:, 0] = ~_fixed_to_plane(model, self.env, self.keep_out.mounting)
        # (S, O) m: the clearance each segment keeps from each obstacle; the tip's is none (it may touch, not enter)
        self.clearance = np.array([[o.clearance for o in self.obstacles]] * S).reshape(S, len(self.obstacles))
        if tip:
            self.clearance[-1] = 0.0
            if tip_only:
                self.mask[:-1, len(self.obstacles) - len(tip_only):] = False
        self.need = np.maximum(self.clearance - slack, 0.0)
        self._plain: Checker | None = None if tip else self

    def leaving(self, q) -> Checker:
        """The checker for a path that starts at ``q``: this one, unless the tool's tip is already at a surface
        there (seated, touching: the tip check does not hold at the start), then the one without the tip
        check (what the approach to that reference was checked with) for the way out."""
        if self._plain is self or self.clear(np.asarray(q, float)[None])[0]:
            return self
        if self._plain is None:
            self._plain = Checker(self.model, self.keep_out, self.slack)
        return self._plain

    def margins(self, Q, chunk: int = 4096) -> np.ndarray:
        """``(N, S, O)``: envelope distance minus required clearance (negative = violation; +inf = unchecked)."""
        Q = np.atleast_2d(np.asarray(Q, float))
        out = np.full((len(Q), len(self.env.a), len(self.obstacles)), np.inf)
        if not self.obstacles:
            return out
        for s in range(0, len(Q), chunk):
            A, B, r = capsules(self.model, Q[s:s + chunk], self.env, ops=self._ops)
            for o, ob in enumerate(self.obstacles):
                d = _plane_distance(A, B, ob) if isinstance(ob, Plane) else self._box(A, B, r, ob)
                m = d - r[None, :] - self.need[None, :, o]
                out[s:s + chunk, :, o] = np.where(self.mask[None, :, o], m, np.inf)
        return out

    @staticmethod
    def _box(A, B, r, box: Box, near: float = 0.05) -> np.ndarray:
        """Segment-box distances, searched only where a cheap lower bound (centre distances minus the half
        segment and the box's circumradius) comes within ``near`` of touching; elsewhere the bound itself,
        which never overstates a margin."""
        lb = (np.linalg.norm((A + B) / 2 - box.center, axis=-1) - np.linalg.norm(B - A, axis=-1) / 2
              - float(np.linalg.norm(box.half)))
        close = lb < r[None, :] + box.clearance + near
        if close.any():
            lb[close] = _box_distance(A[close], B[close], box)
        return lb

    def clear(self, Q) -> np.ndarray:
        """``(N,)`` bool: no link within any obstacle's clearance."""
        M = self.margins(Q)
        return np.all(M >= 0, axis=(1, 2)) if M.size else np.ones(len(np.atleast_2d(Q)), bool)

    def hits(self, Q) -> list[Hit | None]:
        """Per configuration: the worst violation, or None when clear."""
        M = self.margins(Q)
        out: list[Hit | None] = []
        for m in M:
            if m.size == 0 or m.min() >= 0:
                out.append(None)
                continue
            s, o = np.unravel_index(int(np.argmin(m)), m.shape)
            out.append(self._hit(int(s), int(o), float(m[s, o])))
        return out

    def _hit(self, s: int, o: int, margin: float) -> Hit:
        k = int(self.env.link[s])
        ob = self.obstacles[o]
        return Hit(k, self.env.names[k - 1], ob.name, margin + self.need[s, o], float(self.clearance[s, o]))

    # ---- paths ----------------------------------------------------------------------------------
    def travel(self, qa, qb) -> np.ndarray:
        """``(M,)`` m: how far any point of the envelope can move along the straight joint paths ``qa -> qb``
        (a bound: each joint's travel times the farthest the envelope reaches from its axis)."""
        dq = np.abs(np.atleast_2d(np.asarray(qb, float)) - np.atleast_2d(np.asarray(qa, float)))
        rev = np.array([j.revolute for j in self.model.joints])
        return np.sum(np.where(rev, dq * self.env.reach, dq), axis=1)

    def samples(self, qa, qb, step: float = PATH_STEP) -> int:
        """Samples of the straight joint path qa -> qb so that no envelope point moves more than ``step``."""
        return max(2, int(np.ceil(float(self.travel(qa, qb)[0]) / step)) + 1)

    def _worst(self, Q) -> tuple[np.ndarray, np.ndarray]:
        """Per configuration: the smallest margin and its flat (segment, obstacle) index."""
        M = self.margins(Q).reshape(len(Q), -1)
        if M.shape[1] == 0:
            return np.full(len(Q), np.inf), np.zeros(len(Q), int)
        k = np.argmin(M, axis=1)
        return M[np.arange(len(Q)), k], k

    def scan(self, QA, QB, step: float = PATH_STEP) -> list[Hit | None]:
        """Per straight joint path ``QA[i] -> QB[i]`` (ends included): the worst violation found, or None.

        Equivalent to checking samples no farther apart than ``step`` of envelope motion, but adaptive: a
        margin cannot change faster than the envelope moves (Lipschitz in the path parameter with constant
        ``travel``), so an interval whose end margins prove it clear is not sampled further."""
        QA, QB = np.atleast_2d(np.asarray(QA, float)), np.atleast_2d(np.asarray(QB, float))
        P = len(QA)
        if P == 0:
            return []
        L = self.travel(QA, QB)
        n0 = np.clip(np.ceil(L / step).astype(int) + 1, 2, 33)  # one batch: numpy's overhead, not the count
        path = np.repeat(np.arange(P), n0)
        t = np.concatenate([np.linspace(0.0, 1.0, k) for k in n0])
        m, k = self._worst(QA[path] + t[:, None] * (QB[path] - QA[path]))
        bad_m = np.full(P, np.inf)  # per path: the worst violating margin seen, and where
        bad_k = np.zeros(P, int)

        def record(pp, mm, kk):
            neg = mm < 0
            for a, b, c in zip(pp[neg], mm[neg], kk[neg], strict=True):
                if b < bad_m[a]:
                    bad_m[a], bad_k[a] = b, c

        record(path, m, k)
        # intervals between neighbouring samples of one path; a blocked path is not refined further
        same = path[:-1] == path[1:]
        ip, t0, t1, m0, m1 = path[:-1][same], t[:-1][same], t[1:][same], m[:-1][same], m[1:][same]
        while len(ip):
            width = (t1 - t0) * L[ip]
            keep = ((m0 + m1 - width) / 2 < 0) & (width > step) & ~np.isfinite(bad_m[ip])
            ip, t0, t1, m0, m1 = ip[keep], t0[keep], t1[keep], m0[keep], m1[keep]
            if not len(ip):
                break
            tm = (t0 + t1) / 2
            mm, kk = self._worst(QA[ip] + tm[:, None] * (QB[ip] - QA[ip]))
            record(ip, mm, kk)
            ip, t0, t1, m0, m1 = (np.concatenate([ip, ip]), np.concatenate([t0, tm]), np.concatenate([tm, t1]),
                                  np.concatenate([m0, mm]), np.concatenate([mm, m1]))
        out: list[Hit | None] = []
        O = max(len(self.obstacles), 1)
        for i in range(P):
            if np.isfinite(bad_m[i]):
                s_, o = divmod(int(bad_k[i]), O)
                out.append(self._hit(s_, o, float(bad_m[i])))
            else:
                out.append(None)
        return out

    def path_hit(self, qa, qb, step: float = PATH_STEP) -> Hit | None:
        """The worst violation along the straight joint path ``qa -> qb`` (both ends included), or None."""
        return self.scan(qa, qb, step)[0]

    def paths_clear(self, QA, QB, step: float = PATH_STEP) -> np.ndarray:
        """``(M,)`` bool for M straight joint paths at once."""
        return np.array([h is None for h in self.scan(QA, QB, step)], bool)


def first_hit(model, keep_out: KeepOut | None, q) -> Hit | None:
    """The worst violation at one configuration ``q`` (None: clear). ``keep_out=None``: the default (nothing
    below the base plane)."""
    return Checker(model, keep_out).hits(np.asarray(q, float)[None])[0]


# ---- the keep-out part of a cell document (station-cell/1, and the simulated world's cell section) --------
class KeepOutError(ValueError):
    """A malformed ``mounting`` or ``keep_out`` entry; the message names the field."""


def _number(v, w: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise KeepOutError(f"{w}: expected a number, got {v!r}")
    return float(v)


def _vec3(v, w: str, scale: float = 1.0) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise KeepOutError(f"{w}: expected 3 numbers, got {v!r}")
    return np.array([_number(x, w) for x in v]) * scale


def _unit(v, w: str) -> np.ndarray:
    a = _vec3(v, w)
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        raise KeepOutError(f"{w}: the normal is zero")
    return a / n


def _clearance_of(d: dict, w: str, scale: float, default: float) -> float:
    if "clearance" not in d:
        return default
    c = _number(d["clearance"], f"{w}.clearance")
    if c < 0:
        raise KeepOutError(f"{w}.clearance: must not be negative")
    return c * scale


def _plane_of(name: str, d, w: str, scale: float, clearance: float) -> Plane:
    if not isinstance(d, dict) or set(d) - {"normal", "point", "offset"} or "normal" not in d \
            or ("point" in d) == ("offset" in d):
        raise KeepOutError(f"{w}: a plane is {{normal: [x, y, z], point: [x, y, z]}} or {{normal: [..], offset: d}}")
    normal = _unit(d["normal"], f"{w}.normal")
    if "point" in d:
        return Plane.through(name, _vec3(d["point"], f"{w}.point", scale), normal, clearance)
    return Plane(name, normal, _number(d["offset"], f"{w}.offset") * scale, clearance)


def _box_of(name: str, d, w: str, scale: float, angle: float, clearance: float) -> Box:
    shape = f"{w}: a box is {{min: [..], max: [..]}} or {{center: [..], size: [..], rotation: {{rx, ry, rz}}}}"
    if not isinstance(d, dict):
        raise KeepOutError(shape)
    if set(d) == {"min", "max"}:
        lo, hi = _vec3(d["min"], f"{w}.min", scale), _vec3(d["max"], f"{w}.max", scale)
        if np.any(hi <= lo):
            raise KeepOutError(f"{w}: max must exceed min on every axis")
        return Box.from_corners(name, lo, hi, clearance)
    if set(d) - {"center", "size", "rotation"} or not {"center", "size"} <= set(d):
        raise KeepOutError(shape)
    size = _vec3(d["size"], f"{w}.size", scale)
    if np.any(size <= 0):
        raise KeepOutError(f"{w}.size: every edge must be positive")
    rot = d.get("rotation") or {}
    if not isinstance(rot, dict) or set(rot) - {"rx", "ry", "rz"}:
        raise KeepOutError(f"{w}.rotation: expected {{rx, ry, rz}} (angle unit; R = Rz Ry Rx)")
    from station.kinematics.se3 import rpy_to_matrix

    rpy = np.array([_number(rot.get(k, 0.0), f"{w}.rotation.{k}") * angle for k in ("rx", "ry", "rz")])
    return Box(name, _vec3(d["center"], f"{w}.center", scale), size / 2, rpy_to_matrix(rpy), clearance)


def keep_out_from_dict(doc: dict, where: str, scale: float, angle: float,
                       default_clearance: float = DEFAULT_CLEARANCE) -> KeepOut:
    """``mounting`` and ``keep_out`` of a cell document; lengths in units of ``scale`` m, angles of ``angle``
    rad, clearances default to ``default_clearance`` (m). No ``mounting``: the plane z = 0 of the base frame
    (a table arm); ``mounting: none``: no mounting plane."""
    m = doc.get("mounting", {})
    w = f"{where}: mounting"
    if m == "none":
        mounting = None
    elif isinstance(m, dict):
        plane = {k: v for k, v in m.items() if k != "clearance"}
        plane.setdefault("normal", [0, 0, 1])
        if "point" not in plane:
            plane.setdefault("offset", 0)
        mounting = _plane_of("mounting plane", plane, w, scale, _clearance_of(m, w, scale, default_clearance))
    else:
        raise KeepOutError(f"{w}: expected {{normal, offset|point, clearance}} or the word none (no mounting plane)")
    raw = doc.get("keep_out") or []
    if not isinstance(raw, list):
        raise KeepOutError(f"{where}: keep_out must be a list of {{name, plane|box, clearance}}")
    obstacles: list[Obstacle] = []
    for i, d in enumerate(raw):
        w = f"{where}: keep_out[{i}]"
        if not isinstance(d, dict) or set(d) - {"name", "plane", "box", "clearance"} or ("plane" in d) == ("box" in d):
            raise KeepOutError(f"{w}: expected {{name, plane: {{..}} or box: {{..}}, clearance}}")
        name = str(d.get("name") or f"keep_out[{i}]")
        if name in [o.name for o in obstacles] or name == "mounting plane":
            raise KeepOutError(f"{w}: name {name!r} is used twice (messages name the obstacle)")
        w = f"{w} ({name})"
        c = _clearance_of(d, w, scale, default_clearance)
        obstacles.append(_plane_of(name, d["plane"], f"{w}.plane", scale, c) if "plane" in d
                         else _box_of(name, d["box"], f"{w}.box", scale, angle, c))
    return KeepOut(mounting, tuple(obstacles))


def keep_out_to_doc(ko: KeepOut, length_scale: float = 1.0, angle_scale: float = 1.0,
                    clearance: float | None = None) -> dict:
    """``{mounting, keep_out}`` for a cell document whose length unit is ``length_scale`` m and angle unit
    ``angle_scale`` rad. ``clearance``: write this clearance (m) instead of each obstacle's own."""
    from station.kinematics.se3 import matrix_to_rpy

    def r(x):
        return float(round(x, 9))

    def c(o):
        return r((o.clearance if clearance is None else clearance) / length_scale)

    def plane(p: Plane) -> dict:
        return {"normal": [r(x) for x in p.normal], "offset": r(p.offset / length_scale)}

    out: dict = {"mounting": "none" if ko.mounting is None else {**plane(ko.mounting), "clearance": c(ko.mounting)}}
    items = []
    for o in ko.obstacles:
        if isinstance(o, Plane):
            items.append({"name": o.name, "plane": plane(o), "clearance": c(o)})
        else:
            items.append({"name": o.name, "box": {"center": [r(x / length_scale) for x in o.center],
                                                  "size": [r(2 * x / length_scale) for x in o.half],
                                                  "rotation": dict(zip(("rx", "ry", "rz"),
                                                                       (r(x / angle_scale) for x in
                                                                        matrix_to_rpy(o.rotation)),
                                                                       strict=True))},
                          "clearance": c(o)})
    out["keep_out"] = items
    return out
