"""Kinematic models: joints, parameters, conventions (DH, MDH + Hayati beta, POE), batched FK/Jacobians.

The encoder reading ``q`` and the model joint value are related by ``theta_i = q_i + offset_i``
(revolute) or ``d_i = q_i + offset_i`` (prismatic). Parameter names are stable strings shared by
the solver, results, reports, records and write-back:

``offset.jN``; ``dh.jN.{d,a,alpha,beta}`` (``dh.jN.theta`` for prismatic joints);
``mdh.jN.{alpha,a,beta,d}`` (``mdh.jN.theta`` for prismatic); ``poe.jN.{x,y,z,rz,ry,rx}`` and
``poe.flange.*`` for local POE frames; ``base.{x,y,z,rz,ry,rx}``; ``tcp.{x,y,z,rz,ry,rx}``;
``compliance.jN`` (revolute joints of a model with link masses or a payload, rad per N*m: the joint turns by
``compliance.jN * tau_N(q)`` under their gravity torque, see ``station.kinematics.gravity``).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from station.kinematics import gravity, se3
from station.kinematics.chain import RX, RY, RZ, TX, TY, TZ, Chain, element_twists, forward, forward_fused, fuse

FRAME_AXES = (("x", TX), ("y", TY), ("z", TZ), ("rz", RZ), ("ry", RY), ("rx", RX))
PARALLEL_TOL = np.deg2rad(5.0)  # |alpha| below this (or near pi): next axis near-parallel -> Hayati beta


@dataclass(frozen=True)
class Encoder:
    """Device units <-> SI: ``q = direction * (counts - zero) / (counts_per_unit * gear)``.

    ``counts_per_unit`` is counts per radian (revolute) or per metre (prismatic) at the motor.
    """

    counts_per_unit: float
    gear: float = 1.0
    direction: int = 1
    zero: float = 0.0

    def to_si(self, counts):
        return self.direction * (np.asarray(counts, dtype=float) - self.zero) / (self.counts_per_unit * self.gear)

    def to_counts(self, q):
        return np.asarray(q, dtype=float) * self.counts_per_unit * self.gear * self.direction + self.zero


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str  # "revolute" | "prismatic"
    lower: float
    upper: float
    max_velocity: float  # rad/s or m/s
    max_acceleration: float = 10.0  # rad/s^2 or m/s^2
    encoder: Encoder | None = None

    @property
    def revolute(self) -> bool:
        return self.kind == "revolute"


@dataclass(frozen=True)
class Model:
    """A serial chain with named parameters. Immutable; ``with_params`` returns a changed copy."""

    name: str
    convention: str  # "dh" | "mdh" | "poe"
    joints: tuple[Joint, ...]
    chain: Chain
    param_names: tuple[str, ...]
    params: np.ndarray  # nominal values, SI
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    description: str = ""
    source: dict = field(default_factory=dict)  # convention table as given, for export
    frames: tuple[int, ...] = ()  # chain element after which link k's frame sits (k = 1..n): masses live there
    load: gravity.Load | None = None  # link masses and payload; None: weightless (no gravity deflection)
    # manufacturing tolerances (selector, std SI, quantity) from the model file: see kinematics/tolerances.py
    tolerances: tuple = ()

    # ---- basic facts -------------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.lower for j in self.joints])

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.upper for j in self.joints])

    @property
    def max_velocity(self) -> np.ndarray:
        return np.array([j.max_velocity for j in self.joints])

    def index(self, name: str) -> int:
        try:
            return self.param_names.index(name)
        except ValueError:
            raise KeyError(f"unknown parameter {name!r} for model {self.name}") from None

    def param(self, name: str) -> float:
        return float(self.params[self.index(name)])

    def param_dict(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.param_names, self.params, strict=True)}

    def select(self, spec: str | list[str]) -> list[str]:
        """Expand ``"offsets,tcp,dh.j2.*"`` (groups, exact names, globs) into parameter names."""
        items = spec.split(",") if isinstance(spec, str) else list(spec)
        out: list[str] = []
        for item in (s.strip() for s in items):
            if not item:
                continue
            if item == "compliance" and not self.groups.get(item):
                why = ("has no link masses and no payload: give mass/com in the model file, <inertial> in "
                       "the URDF, or a payload" if self.load is None else "has no joint that gravity can load")
                raise KeyError(f"parameter or group 'compliance': model {self.name} {why}")
            if item in self.groups:
                names = list(self.groups[item])
            elif item in self.param_names:
                names = [item]
            else:
                names = [n for n in self.param_names if fnmatch.fnmatchcase(n, item)]
                if not names:
                    known = ", ".join(sorted(self.groups))
                    raise KeyError(f"unknown parameter or group {item!r} for model {self.name} "
                                   f"(groups: {known})")
            out.extend(n for n in names if n not in out)
        return out

    def with_params(self, values: dict[str, float] | None = None, **kw) -> Model:
        p = self.params.copy()
        for name, v in {**(values or {}), **kw}.items():
            p[self.index(name)] = v
        return replace(self, params=p)

    def with_joints(self, joints: tuple[Joint, ...]) -> Model:
        return replace(self, joints=tuple(joints))

    # ---- gravity load and compliance ---------------------------------------------------------
    def with_payload(self, mass: float, com=(0.0, 0.0, 0.0)) -> Model:
        """This model carrying ``mass`` kg at the tool (centre of mass ``com``, m, in the tool frame);
        0 removes the payload. Link masses are kept."""
        if not (np.isfinite(mass) and mass >= 0):
            raise ValueError(f"payload mass must be a non-negative number of kg, got {mass!r}")
        load = gravity.with_payload(self.load, self.n_joints, self.params, mass, com)
        return self._with_load(load)

    def with_masses(self, masses: dict[int, tuple[float, object]], gravity_vector=None) -> Model:
        """This model with link masses ``{k: (kg, com)}`` (k = 1..n, com in link k's frame, m) replacing
        the present ones; the payload is kept. ``gravity_vector`` (m/s^2, base frame) defaults to the
        present one (or -9.81 along z)."""
        pay = None if self.load is None else self.load.payload
        g = gravity_vector if gravity_vector is not None else (None if self.load is None else self.load.gravity)
        base = self.params if self.load is None else self.load.params
        return self._with_load(gravity.make_load(self.n_joints, base, masses, pay, g))

    def _with_load(self, load: gravity.Load | None) -> Model:
        groups = dict(self.groups)
        groups["compliance"] = _compliance_group(self.chain, self.frames, load, self.joints)
        names, values = list(self.param_names), list(self.params)
        if load is not None:  # a weightless model has no compliance parameters: nothing would load them
            _add_compliance(names, values, self.joints)
        return replace(self, load=load, groups=groups, param_names=tuple(names), params=np.array(values))

    @cached_property
    def compliance_index(self) -> tuple[np.ndarray, np.ndarray]:
        """``(joints, params)``: joint index and parameter index of every ``compliance.jN``."""
        js = [i for i in range(self.n_joints) if f"compliance.j{i + 1}" in self.param_names]
        return np.array(js, dtype=int), np.array([self.index(f"compliance.j{i + 1}") for i in js], dtype=int)

    def gravity_torque(self, q, derivative: bool = False):
        """Gravity torque on each joint ``(N, n)`` at encoder values q (N*m; N for prismatic joints), on the
        load's frozen geometry (zeros without a load); with ``derivative`` also ``d tau/d q`` ``(N, n, n)``."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if self.load is None:
            z = np.zeros(q.shape)
            return (z, np.zeros(q.shape + (q.shape[1],))) if derivative else z
        return gravity.torques(self.chain, np.array(self.frames, dtype=int), self.load, q, derivative)

    def deflection(self, q, params=None) -> np.ndarray:
        """Joint value change ``(N, n)`` under gravity: ``compliance.jN * tau_N(q)`` (0 without a load)."""
        q, p, _ = self._prep(q, params)
        return self._deflection(q, p)[0]

    def _deflection(self, q, p, derivative: bool = False):
        js, ps = self.compliance_index
        if self.load is None or not len(js):
            return np.zeros(q.shape), None, None
        c = p[ps]
        if not c.any() and not derivative:
            return np.zeros(q.shape), None, None
        out = self.gravity_torque(q, derivative)
        tau, dtau = out if derivative else (out, None)
        d = np.zeros(q.shape)
        d[:, js] = c * tau[:, js]
        return d, tau, dtau

    # ---- kinematics --------------------------------------------------------------------------
    def _prep(self, q, params):
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        q = np.atleast_2d(q)
        if q.shape[1] != self.n_joints:
            raise ValueError(f"model {self.name} has {self.n_joints} joints, got {q.shape[1]} values")
        p = self.params if params is None else np.asarray(params, dtype=float)
        return q, p, single

    def fk(self, q, params=None) -> np.ndarray:
        """Tool (TCP) transform in the base frame: ``(N,4,4)``, or ``(4,4)`` for one pose."""
        q, p, single = self._prep(q, params)
        T = forward_fused(self._fused(p), q + self._deflection(q, p)[0])
        return T[0] if single else T

    def _fused(self, p: np.ndarray):
        """The chain fused for parameter vector ``p`` (the last few kept: IK and planning reuse one)."""
        cache = self.__dict__.setdefault("_fused_cache", {})
        key = p.tobytes()
        f = cache.get(key)
        if f is None:
            if len(cache) >= 8:  # a solver's iterations: each vector once
                cache.clear()
            f = cache[key] = fuse(self.chain, p)
        return f

    def fk_and_jacobian_q(self, q, params=None) -> tuple[np.ndarray, np.ndarray]:
        """``(T, Jq)`` of :meth:`jacobians` without the parameter Jacobian (what IK and jogging need): through
        the fused chain, a few times faster. Under a gravity load with compliance the full routine is used."""
        q, p, _ = self._prep(q, params)
        js, ps = self.compliance_index
        if self.load is not None and len(js) and p[ps].any():  # zero compliance: no deflection, no stiffness term
            T, Jq, _ = self.jacobians(q, p)
            return T, Jq
        return forward_fused(self._fused(p), q, jacobian=True)

    def position(self, q, params=None) -> np.ndarray:
        """Tool position ``(N,3)`` (m)."""
        T = self.fk(q, params)
        return T[..., :3, 3]

    def jacobians(self, q, params=None):
        """``(T, Jq, Jp)``: tool transforms ``(N,4,4)``, joint Jacobian ``(N,6,n)`` and parameter
        Jacobian ``(N,6,P)``. Rows are tool position (x,y,z) then world angular velocity.

        With a gravity load: the column of ``compliance.jN`` is ``tau_N(q)`` times the joint's twist, and
        ``Jq`` includes the change of the deflection with q (the gravity stiffness), so both are exact
        derivatives of :meth:`fk`."""
        q, p, _ = self._prep(q, params)
        d, tau, dtau = self._deflection(q, p, derivative=self.load is not None)
        T, prefix = forward(self.chain, q + d, p, keep_prefix=True)
        tw = element_twists(self.chain, T, prefix)
        N = q.shape[0]
        Jq = np.zeros((N, 6, self.n_joints))
        Jp = np.zeros((N, 6, len(self.param_names)))
        for k in range(self.chain.n_elements):
            if self.chain.joint[k] >= 0:
                Jq[:, :, self.chain.joint[k]] += tw[:, :, k]
            if self.chain.param[k] >= 0:
                Jp[:, :, self.chain.param[k]] += tw[:, :, k]
        if tau is not None:
            js, ps = self.compliance_index
            Jp[:, :, ps] = Jq[:, :, js] * tau[:, None, js]
            # theta = q + C tau(q): d theta / d q = I + C dtau/dq (compliance only on its joints)
            D = np.zeros((self.n_joints, self.n_joints))
            D[js, js] = p[ps]
            if D.any():
                Jq = Jq + np.einsum("nri,ij,njk->nrk", Jq, D, dtau)
        return T, Jq, Jp

    def jacobian_q(self, q, params=None) -> np.ndarray:
        return self.fk_and_jacobian_q(q, params)[1]

    def jacobian_params(self, q, params=None, names: list[str] | None = None) -> np.ndarray:
        Jp = self.jacobians(q, params)[2]
        return Jp if names is None else Jp[:, :, [self.index(n) for n in names]]

    def within_limits(self, q, margin: float = 0.0) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        return np.all((q >= self.lower + margin) & (q <= self.upper - margin), axis=1)

    def ik(self, target, q0, **kw):
        from station.kinematics.ik import solve_ik

        return solve_ik(self, target, q0, **kw)


# ---- builders ---------------------------------------------------------------------------------
class _Builder:
    def __init__(self) -> None:
        self.axis: list[int] = []
        self.param: list[int] = []
        self.joint: list[int] = []
        self.const: list[float] = []
        self.names: list[str] = []
        self.values: list[float] = []
        self.frames: list[int] = []  # element after which link k's frame sits

    def link_frame(self) -> None:
        """The frame after the last element added is the frame of the next link (masses are given in it)."""
        self.frames.append(len(self.axis) - 1)

    def add(self, axis: int, name: str | None, value: float = 0.0, joint: int = -1, const: float = 0.0):
        self.axis.append(axis)
        self.joint.append(joint)
        self.const.append(const)
        if name is None:
            self.param.append(-1)
        else:
            self.param.append(len(self.names))
            self.names.append(name)
            self.values.append(float(value))

    def frame(self, prefix: str, T: np.ndarray) -> None:
        """Six elements Tx Ty Tz Rz Ry Rx reproducing the fixed transform ``T``."""
        rx, ry, rz = se3.matrix_to_rpy(T[:3, :3])
        vals = dict(x=T[0, 3], y=T[1, 3], z=T[2, 3], rx=rx, ry=ry, rz=rz)
        for key, axis in FRAME_AXES:
            self.add(axis, f"{prefix}.{key}", vals[key])

    def chain(self) -> Chain:
        return Chain(np.array(self.axis, dtype=int), np.array(self.param, dtype=int),
                     np.array(self.joint, dtype=int), np.array(self.const, dtype=float))


def _near_parallel(alpha: float) -> bool:
    a = abs(np.remainder(alpha + np.pi / 2, np.pi) - np.pi / 2)
    return a < PARALLEL_TOL


def _pose(d: dict | None) -> np.ndarray:
    d = d or {}
    return se3.pose_to_matrix(np.array([d.get(k, 0.0) for k in ("x", "y", "z", "rx", "ry", "rz")]), "rpy")


def _finish(b: _Builder, name, convention, joints, groups, base, tool, description, source, *, compliance=None,
            masses=None, payload=None, gravity_vector=None) -> Model:
    """Common tail of every builder. ``compliance`` (per joint, rad per N*m; prismatic entries ignored),
    ``masses`` ``{k: (kg, com)}`` in link k's frame, ``payload`` ``(kg, com in the tool frame)``,
    ``gravity_vector`` (m/s^2, base frame; default -9.81 along z)."""
    n = len(joints)
    chain = b.chain()
    load = gravity.make_load(n, np.array(b.values), masses, payload, gravity_vector)
    if load is not None or any(compliance or []):
        _add_compliance(b.names, b.values, joints, compliance)
    groups = {k: tuple(v) for k, v in groups.items()}
    groups["offsets"] = tuple(f"offset.j{i + 1}" for i in range(n))
    groups["tcp"] = ("tcp.x", "tcp.y", "tcp.z")
    groups["tcp6"] = tuple(f"tcp.{k}" for k, _ in FRAME_AXES)
    groups["base"] = tuple(f"base.{k}" for k, _ in FRAME_AXES)
    groups["base_position"] = ("base.x", "base.y", "base.z")
    groups["links"] = groups["dh"]
    # every geometric parameter a position measurement can see: the tool orientation cannot (tcp6 adds it)
    groups["full"] = groups["offsets"] + groups["dh"] + groups["tcp"] + groups["base"]
    groups["compliance"] = _compliance_group(chain, b.frames, load, joints)
    return Model(name, convention, tuple(joints), chain, tuple(b.names), np.array(b.values), groups, description,
                 {**source, "base": base or {}, "tool": tool or {}}, tuple(b.frames), load)


def _add_compliance(names: list[str], values: list[float], joints, compliance=None) -> None:
    """``compliance.jN`` of every revolute joint, after every chain parameter (the chain's indices stay)."""
    for i, jt in enumerate(joints):
        if jt.revolute and f"compliance.j{i + 1}" not in names:
            names.append(f"compliance.j{i + 1}")
            values.append(float(compliance[i]) if compliance else 0.0)


def _compliance_group(chain: Chain, frames, load, joints) -> tuple[str, ...]:
    """``compliance.jN`` of the revolute joints gravity can load: some mass beyond the joint, and an axis
    that is not fixed along gravity (the first joint of an upright arm never carries a gravity torque)."""
    if load is None:
        return ()
    n = len(joints)
    mv = np.flatnonzero(chain.joint >= 0)
    e = mv[np.argsort(chain.joint[mv])]
    elem = np.array([frames[k - 1] if k <= n else chain.n_elements - 1 for k in load.link])
    _, prefix = forward(chain, np.zeros((1, n)), load.params, keep_prefix=True)
    g = load.gravity / max(np.linalg.norm(load.gravity), 1e-300)
    out = []
    for i, jt in enumerate(joints):
        if not jt.revolute or not (elem >= e[i]).any():
            continue
        w = prefix[0, e[i], :3, chain.axis[e[i]] % 3]
        fixed_axis = not any(chain.axis[e[j]] >= 3 for j in range(n) if e[j] < e[i])
        if fixed_axis and np.linalg.norm(np.cross(w, g)) < 1e-9:
            continue
        out.append(f"compliance.j{i + 1}")
    return tuple(out)


def _base_and_tool_start(b: _Builder, base: dict | None) -> None:
    T = _pose(base)
    rx, ry, rz = se3.matrix_to_rpy(T[:3, :3])
    vals = dict(x=T[0, 3], y=T[1, 3], z=T[2, 3], rx=rx, ry=ry, rz=rz)
    for key, axis in FRAME_AXES:
        b.add(axis, f"base.{key}", vals[key])


def from_dh(name: str, joints: list[Joint], links: list[dict], *, base=None, tool=None,
            offsets=None, description: str = "", **physics) -> Model:
    """Standard DH: link i = ``Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)``. ``links[i]`` has keys
    ``a, d, alpha, theta`` (and optional ``beta``), SI. ``theta`` of a revolute joint and ``d`` of a
    prismatic one are the joint value at ``q = 0`` (a constant, not a parameter)."""
    b = _Builder()
    _base_and_tool_start(b, base)
    offsets = offsets or [0.0] * len(joints)
    dh_names: list[str] = []
    for i, (jt, ln) in enumerate(zip(joints, links, strict=True)):
        j = f"j{i + 1}"
        if jt.revolute:
            b.add(RZ, f"offset.{j}", offsets[i], joint=i, const=ln.get("theta", 0.0))
            b.add(TZ, f"dh.{j}.d", ln.get("d", 0.0))
            dh_names.append(f"dh.{j}.d")
        else:
            b.add(RZ, f"dh.{j}.theta", ln.get("theta", 0.0))
            b.add(TZ, f"offset.{j}", offsets[i], joint=i, const=ln.get("d", 0.0))
            dh_names.append(f"dh.{j}.theta")
        b.add(TX, f"dh.{j}.a", ln.get("a", 0.0))
        b.add(RX, f"dh.{j}.alpha", ln.get("alpha", 0.0))
        b.add(RY, f"dh.{j}.beta", ln.get("beta", 0.0))
        b.link_frame()  # DH frame i (distal end of link i), as published mass tables use
        dh_names += [f"dh.{j}.a", f"dh.{j}.alpha"]
        if _near_parallel(ln.get("alpha", 0.0)) and i < len(joints) - 1:
            dh_names.append(f"dh.{j}.beta")
    _tool(b, tool)
    return _finish(b, name, "dh", joints, {"dh": dh_names, "beta": [f"dh.j{i + 1}.beta" for i in
                                                                    range(len(joints))]},
                   base, tool, description, {"links": links}, **physics)


def from_mdh(name: str, joints: list[Joint], links: list[dict], *, base=None, tool=None,
             offsets=None, description: str = "", **physics) -> Model:
    """Modified DH (Craig) with Hayati beta: link i = ``Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)``,
    where alpha and a describe the previous axis to this one."""
    b = _Builder()
    _base_and_tool_start(b, base)
    offsets = offsets or [0.0] * len(joints)
    names: list[str] = []
    for i, (jt, ln) in enumerate(zip(joints, links, strict=True)):
        j = f"j{i + 1}"
        b.add(RX, f"mdh.{j}.alpha", ln.get("alpha", 0.0))
        b.add(TX, f"mdh.{j}.a", ln.get("a", 0.0))
        b.add(RY, f"mdh.{j}.beta", ln.get("beta", 0.0))
        names += [f"mdh.{j}.alpha", f"mdh.{j}.a"]
        if i > 0 and _near_parallel(ln.get("alpha", 0.0)):
            names.append(f"mdh.{j}.beta")
        if jt.revolute:
            b.add(RZ, f"offset.{j}", offsets[i], joint=i, const=ln.get("theta", 0.0))
            b.add(TZ, f"mdh.{j}.d", ln.get("d", 0.0))
            names.append(f"mdh.{j}.d")
        else:
            b.add(RZ, f"mdh.{j}.theta", ln.get("theta", 0.0))
            b.add(TZ, f"offset.{j}", offsets[i], joint=i, const=ln.get("d", 0.0))
            names.append(f"mdh.{j}.theta")
        b.link_frame()  # Craig frame i, on joint i's axis
    _tool(b, tool)
    return _finish(b, name, "mdh", joints, {"dh": names, "beta": [f"mdh.j{i + 1}.beta" for i in
                                                                  range(len(joints))]},
                   base, tool, description, {"links": links}, **physics)


def _axis_frame(w: np.ndarray, point: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    z = w / np.linalg.norm(w)
    x = x_hint - z * (x_hint @ z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    G = np.eye(4)
    G[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    G[:3, 3] = point
    return G


def from_poe(name: str, joints: list[Joint], screws: list[dict], home: np.ndarray, *, base=None,
             tool=None, offsets=None, description: str = "", **physics) -> Model:
    """Product of exponentials ``T = e^[S1]q1 ... e^[Sn]qn M`` with space-frame screws given as
    ``{"axis": w, "point": p}`` (revolute) or ``{"axis": v}`` (prismatic), and ``M`` = flange at home.

    Compiled to the equivalent *local* POE form ``G1 Rz(q1) G1^-1 G2 Rz(q2) ... Gn^-1 M`` whose fixed
    frames ``poe.jN.*`` and ``poe.flange.*`` carry the identifiable geometry."""
    b = _Builder()
    _base_and_tool_start(b, base)
    offsets = offsets or [0.0] * len(joints)
    prev = np.eye(4)
    names: list[str] = []
    for i, (jt, sc) in enumerate(zip(joints, screws, strict=True)):
        w = np.asarray(sc["axis"], dtype=float)
        pt = np.asarray(sc.get("point", [0.0, 0.0, 0.0]), dtype=float)
        G = _axis_frame(w, pt, prev[:3, 0])
        b.frame(f"poe.j{i + 1}", se3.invert(prev) @ G)
        names += [f"poe.j{i + 1}.{k}" for k, _ in FRAME_AXES]
        b.add(RZ if jt.revolute else TZ, f"offset.j{i + 1}", offsets[i], joint=i)
        b.link_frame()  # the joint frame (z along the joint axis), turned by the joint
        prev = G
    b.frame("poe.flange", se3.invert(prev) @ np.asarray(home, dtype=float))
    names += [f"poe.flange.{k}" for k, _ in FRAME_AXES]
    _tool(b, tool)
    src = {"screws": [{k: np.asarray(v, float).tolist() for k, v in s.items()} for s in screws],
           "home": np.asarray(home, float).tolist()}
    return _finish(b, name, "poe", joints, {"dh": names}, base, tool, description, src, **physics)


def _tool(b: _Builder, tool: dict | None) -> None:
    T = _pose(tool)
    rx, ry, rz = se3.matrix_to_rpy(T[:3, :3])
    vals = dict(x=T[0, 3], y=T[1, 3], z=T[2, 3], rx=rx, ry=ry, rz=rz)
    for key, axis in FRAME_AXES:
        b.add(axis, f"tcp.{key}", vals[key])


def screws_of(model: Model, params=None) -> tuple[list[dict], np.ndarray]:
    """Space-frame screws and flange home pose of ``model`` at ``q = 0`` (without base and tool),
    e.g. to build the POE twin of a DH model."""
    n = model.n_joints
    p = model.params if params is None else params
    zero_base = p.copy()
    for k, _ in FRAME_AXES:
        zero_base[model.index(f"base.{k}")] = 0.0
        zero_base[model.index(f"tcp.{k}")] = 0.0
    # evaluate where every joint value equals its constant: offsets are exported separately
    q0 = -np.array([[p[model.index(f"offset.j{i + 1}")] for i in range(n)]])
    T, prefix = forward(model.chain, q0, zero_base, keep_prefix=True)
    screws = []
    for i, jt in enumerate(model.joints):
        k = int(np.flatnonzero(model.chain.joint == i)[0])
        F = prefix[0, k]
        ax = int(model.chain.axis[k]) % 3
        # the joint element rotates/translates about the axis of the frame before it
        if jt.revolute:
            screws.append({"axis": F[:3, ax].copy(), "point": F[:3, 3].copy()})
        else:
            screws.append({"axis": F[:3, ax].copy()})
    return screws, T[0]
