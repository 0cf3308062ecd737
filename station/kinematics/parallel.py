"""Parallel robots: a Gough-Stewart 6-6 platform and the seed's planar two-strut robot.

The actuator vector ``q`` holds leg (strut) lengths as the devices report them; the geometric length,
anchor to anchor, is ``q_k + offset_k`` (the same rule as a prismatic joint of a serial model). Inverse
kinematics is closed form. Forward kinematics of the hexapod is Newton's method on the analytic
Jacobian, started at the home pose (or a given guess) and continued from home along the straight line in
leg space when a direct start does not converge; the planar robot's forward kinematics is closed form
(two circles meet), with its assembly branch fixed by the model. Failures are one-line reasons: outside
the workspace, singular, or another assembly mode.

Parameter names (shared by world files, results and maps): ``anchor.base.K.{x,y,z}``,
``anchor.platform.K.{x,y,z}``, ``leg.K.offset``, ``tcp.{x,y,z,rz,ry,rx}`` (hexapod; the tool on the
platform), ``pivot.K.{x,y}``, ``strut.K.offset`` (planar struts). SI throughout.

``ParallelModel`` offers the part of :class:`station.kinematics.Model`'s interface that does not need a
serial chain (``fk``, ``position``, ``jacobians``, ``ik``, parameters, joints, limits), so the simulated
world can hold a parallel robot's truth."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.kinematics import se3
from station.kinematics.ik import IKResult
from station.kinematics.model import FRAME_AXES, Joint, Model
from station.kinematics.modelformat import ModelFileError

GOUGH_STEWART = "gough-stewart"
PLANAR_STRUTS = "planar-struts"
TYPES = (GOUGH_STEWART, PLANAR_STRUTS)

FK_TOL = 1e-11  # m: leg length residual at which Newton stops
FK_MAX_ITER = 40
CONTINUATION_STEPS = 12
LIMIT_TOL = 1e-9  # m: closed-form IK landing on a limit is inside it
SINGULAR_COND = 1e8  # condition number (rotation columns scaled by the platform size) called singular
TCP_KEYS = tuple(k for k, _ in FRAME_AXES)  # x, y, z, rz, ry, rx


class ParallelKinematicsError(ValueError):
    """A configuration the model cannot assemble or a pose it cannot reach; one line."""


class SerialOnlyError(ModelFileError):
    """A serial-chain feature (e.g. parametric identification) asked of a parallel model."""


@dataclass(frozen=True)
class FKResult:
    T: np.ndarray  # (N,4,4) tool pose (identity / NaN where not ok)
    ok: np.ndarray  # (N,) bool
    reason: list[str]  # "" where ok
    iterations: int


@dataclass(frozen=True)
class ParallelModel:
    """A parallel robot with named parameters. Immutable; ``with_params`` returns a changed copy."""

    name: str
    type: str  # GOUGH_STEWART | PLANAR_STRUTS
    joints: tuple[Joint, ...]
    param_names: tuple[str, ...]
    params: np.ndarray
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    description: str = ""
    home: np.ndarray | None = None  # (6,) platform pose x, y, z, rx, ry, rz (fixed-axis rpy), hexapod
    branch: int = 1  # planar struts: +1 hinge left of pivot1 -> pivot2, -1 right
    convention: str = "parallel"
    kind: str = "parallel"

    # The parameter-vector bookkeeping is the serial model's, borrowed rather than copied.
    n_joints = Model.n_joints
    lower = Model.lower
    upper = Model.upper
    max_velocity = Model.max_velocity
    index = Model.index
    param = Model.param
    param_dict = Model.param_dict
    select = Model.select
    with_params = Model.with_params
    with_joints = Model.with_joints
    within_limits = Model.within_limits

    @property
    def chain(self):
        raise SerialOnlyError(f"model {self.name} is a parallel robot ({self.type}): parametric identification "
                              f"needs a serial chain; calibrate it with 'station map'")

    @property
    def pose_columns(self) -> tuple[str, ...]:
        """Pose components that fix a configuration: ``x, y`` (planar) or ``x, y, z, rx, ry, rz``."""
        return ("x", "y") if self.type == PLANAR_STRUTS else ("x", "y", "z", "rx", "ry", "rz")

    # ---- geometry ---------------------------------------------------------------------------
    def geometry(self, params=None) -> dict[str, np.ndarray]:
        """Named arrays (SI): hexapod ``base (6,3)``, ``platform (6,3)``, ``offset (6,)``, ``tool (4,4)``;
        planar ``pivots (2,2)``, ``offset (2,)``."""
        p = self.params if params is None else np.asarray(params, dtype=float)
        if self.type == GOUGH_STEWART:
            t = dict(zip(TCP_KEYS, p[42:48], strict=True))
            tool = se3.pose_to_matrix(np.array([t["x"], t["y"], t["z"], t["rx"], t["ry"], t["rz"]]), "rpy")
            return {"base": p[0:18].reshape(6, 3), "platform": p[18:36].reshape(6, 3), "offset": p[36:42],
                    "tool": tool}
        return {"pivots": p[0:4].reshape(2, 2), "offset": p[4:6]}

    @property
    def home_q(self) -> np.ndarray:
        """Actuator values at the home pose (hexapod), or the middle of the limits (planar)."""
        if self.type == GOUGH_STEWART:
            g = self.geometry()
            return self._gs_ik_platform(se3.pose_to_matrix(self.home, "rpy")[None], g)[0][0]
        return (self.lower + self.upper) / 2

    # ---- inverse kinematics (closed form) ---------------------------------------------------
    def _gs_ik_platform(self, P: np.ndarray, g: dict):
        """Leg lengths minus offsets for platform poses ``P (N,4,4)``; also the Jacobian parts."""
        ra = np.einsum("nij,kj->nki", P[:, :3, :3], g["platform"])  # (N,6,3) platform anchors, world dirs
        leg = P[:, None, :3, 3] + ra - g["base"][None]
        length = np.linalg.norm(leg, axis=2)
        return length - g["offset"][None], leg, length, ra

    def ik_closed(self, target, params=None, check_limits: bool = True) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """``(q (N,n), ok (N,), reasons)`` for tool poses ``(N,4,4)`` or, planar, positions ``(N,2|3)``.
        Not ok: in another assembly mode than the model's, or (``check_limits``) outside the actuator limits."""
        g = self.geometry(params)
        target = np.asarray(target, dtype=float)
        if self.type == GOUGH_STEWART:
            if target.shape[-2:] != (4, 4):
                raise ParallelKinematicsError(f"model {self.name}: a hexapod's inverse kinematics needs the full "
                                              f"pose (position and orientation)")
            T = target.reshape(-1, 4, 4)
            P = T @ se3.invert(g["tool"])
            q, leg, length, ra = self._gs_ik_platform(P, g)
            sign = np.sign(np.linalg.det(self._gs_jacobian(leg, length, ra)))
            mode_ok = sign == self._gs_home_sign(g)
        else:
            h = target[..., :3, 3] if target.shape[-2:] == (4, 4) else target
            h = np.atleast_2d(h)[:, :2]
            c = g["pivots"]
            q = np.linalg.norm(h[:, None, :] - c[None], axis=2) - g["offset"][None]
            side = _cross2(c[1] - c[0], h - c[0])
            mode_ok = np.sign(side) == self.branch
        inside = self.within_limits(q, -LIMIT_TOL) if check_limits else np.ones(len(q), dtype=bool)
        reasons = []
        for i in range(len(q)):
            if not mode_ok[i]:
                reasons.append("the pose needs another assembly mode (other side of a singularity)"
                               if self.type == GOUGH_STEWART else
                               f"the hinge would lie on the other side of the pivot line (assembly branch "
                               f"{-self.branch}; the model has {self.branch})")
            elif not inside[i]:
                k = int(np.flatnonzero((q[i] < self.lower - LIMIT_TOL) | (q[i] > self.upper + LIMIT_TOL))[0])
                reasons.append(f"actuator {k + 1} would be {q[i, k]:.6g} m, outside its limits "
                               f"[{self.lower[k]:.6g}, {self.upper[k]:.6g}] m")
            else:
                reasons.append("")
        return q, mode_ok & inside, reasons

    def ik(self, target, q0=None, **_ignored) -> IKResult:
        """Closed-form inverse kinematics with the serial model's result type (``q0`` is not needed)."""
        q, ok, _ = self.ik_closed(target, _ignored.get("params"))
        N = len(q)
        return IKResult(q, ok, np.zeros(N), np.zeros(N), 0)

    # ---- forward kinematics -----------------------------------------------------------------
    def fk_solve(self, q, params=None, guess=None) -> FKResult:
        """Forward kinematics without raising: tool poses, a per-row ok flag and reason."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if q.shape[1] != self.n_joints:
            raise ValueError(f"model {self.name} has {self.n_joints} actuators, got {q.shape[1]} values")
        g = self.geometry(params)
        if self.type == PLANAR_STRUTS:
            return self._planar_fk(q, g)
        return self._gs_fk(q, g, guess)

    def fk(self, q, params=None, guess=None) -> np.ndarray:
        """Tool pose ``(N,4,4)`` (or ``(4,4)`` for one configuration); raises
        :class:`ParallelKinematicsError` naming the first configuration that cannot be assembled."""
        single = np.asarray(q).ndim == 1
        res = self.fk_solve(q, params, guess)
        if not res.ok.all():
            i = int(np.flatnonzero(~res.ok)[0])
            qi = np.atleast_2d(np.asarray(q, dtype=float))[i]
            where = "" if single else f"configuration {i + 1}: "
            raise ParallelKinematicsError(f"model {self.name}: {where}actuators "
                                          f"[{', '.join(f'{x:.6g}' for x in qi)}] m: {res.reason[i]}")
        return res.T[0] if single else res.T

    def position(self, q, params=None) -> np.ndarray:
        return self.fk(q, params)[..., :3, 3]

    def _planar_fk(self, q: np.ndarray, g: dict) -> FKResult:
        c = g["pivots"]
        L = q + g["offset"][None]
        d_vec = c[1] - c[0]
        d = float(np.linalg.norm(d_vec))
        e = d_vec / d
        n = np.array([-e[1], e[0]])  # left of pivot1 -> pivot2
        a = (L[:, 0] ** 2 - L[:, 1] ** 2 + d * d) / (2 * d)
        h2 = L[:, 0] ** 2 - a * a
        tol = max(d, float(np.max(np.abs(L), initial=0.0))) / SINGULAR_COND ** 0.5  # hinge height called singular
        N = len(q)
        ok = np.ones(N, dtype=bool)
        reason = [""] * N
        for i in range(N):
            if np.any(L[i] <= 0):
                ok[i], reason[i] = False, "a strut length is not positive"
            elif h2[i] < -tol * tol:
                ok[i], reason[i] = False, "the struts cannot meet (outside the workspace)"
            elif h2[i] < tol * tol:
                ok[i], reason[i] = False, "singular: both struts lie on the pivot line"
        h = np.sqrt(np.maximum(h2, 0.0))
        pos = c[0][None] + a[:, None] * e[None] + (self.branch * h)[:, None] * n[None]
        T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
        T[:, :2, 3] = pos
        T[~ok] = np.nan
        return FKResult(T, ok, reason, 0)

    # -- hexapod ---------------------------------------------------------------------------
    @staticmethod
    def _gs_jacobian(leg: np.ndarray, length: np.ndarray, ra: np.ndarray) -> np.ndarray:
        """d(leg lengths)/d(platform twist [v; w], world frame at the platform origin): ``(N,6,6)``."""
        u = leg / length[..., None]
        return np.concatenate([u, np.cross(ra, u)], axis=2)

    def _scale(self, g: dict) -> float:
        return max(float(np.max(np.linalg.norm(g["platform"], axis=1))), 1e-3)

    def _gs_home_sign(self, g: dict) -> float:
        P = se3.pose_to_matrix(self.home, "rpy")[None]
        _, leg, length, ra = self._gs_ik_platform(P, g)
        return float(np.sign(np.linalg.det(self._gs_jacobian(leg, length, ra)))[0])

    def _gs_newton(self, L: np.ndarray, P: np.ndarray, g: dict):
        """Newton on the platform pose for leg lengths ``L (N,6)`` from ``P (N,4,4)``.
        Returns (P, converged, residual, cond, iterations)."""
        P = P.copy()
        N = len(L)
        s = self._scale(g)
        step_p, step_w = 0.25 * float(np.max(L)), 0.3
        conv = np.zeros(N, dtype=bool)
        res = np.full(N, np.inf)
        it = 0

        def residual(Pk, Lk):
            _, leg, length, ra = self._gs_ik_platform(Pk, g)
            return length - Lk, leg, length, ra

        r, leg, length, ra = residual(P, L)
        for it in range(1, FK_MAX_ITER + 1):  # noqa: B007
            res = np.max(np.abs(r), axis=1)
            conv = res < FK_TOL
            act = ~conv & np.isfinite(res)
            if not act.any():
                break
            J = self._gs_jacobian(leg[act], length[act], ra[act])
            try:
                d = -np.linalg.solve(J, r[act][..., None])[..., 0]
            except np.linalg.LinAlgError:
                JT = np.swapaxes(J, 1, 2)
                A = JT @ J + 1e-12 * np.eye(6)
                d = -np.linalg.solve(A, (JT @ r[act][..., None]))[..., 0]
            k = np.minimum(1.0, np.minimum(step_p / np.maximum(np.linalg.norm(d[:, :3], axis=1), 1e-300),
                                           step_w / np.maximum(np.linalg.norm(d[:, 3:], axis=1), 1e-300)))
            d *= k[:, None]
            # backtracking: accept a step only if it lowers the worst leg residual
            Pa = P[act]
            old = res[act]
            lam = np.ones(len(d))
            for _ in range(8):
                Pn = _step(Pa, d * lam[:, None])
                rn = residual(Pn, L[act])[0]
                worse = np.max(np.abs(rn), axis=1) > old * (1 - 1e-4 * lam) + FK_TOL
                if not worse.any():
                    break
                lam = np.where(worse, lam * 0.5, lam)
            P[act] = _step(Pa, d * lam[:, None])
            r, leg, length, ra = residual(P, L)
        res = np.max(np.abs(r), axis=1)
        conv = res < FK_TOL * 10
        J = self._gs_jacobian(leg, length, ra) * np.r_[np.ones(3), np.full(3, 1 / s)][None, None, :]
        with np.errstate(invalid="ignore", over="ignore"):
            cond = np.linalg.cond(J) if N else np.zeros(0)
        return P, conv, res, cond, it

    def _gs_fk(self, q: np.ndarray, g: dict, guess) -> FKResult:
        N = len(q)
        L = q + g["offset"][None]
        tool = g["tool"]
        home = se3.pose_to_matrix(self.home, "rpy")
        if guess is None:
            P0 = np.broadcast_to(home, (N, 4, 4)).copy()
        else:
            P0 = np.asarray(guess, dtype=float).reshape(-1, 4, 4) @ se3.invert(tool)
            P0 = np.broadcast_to(P0, (N, 4, 4)).copy()
        home_sign = self._gs_home_sign(g)
        P, conv, res, cond, it = self._gs_newton(L, P0, g)

        def mode(Pk):
            _, leg, length, ra = self._gs_ik_platform(Pk, g)
            return np.sign(np.linalg.det(self._gs_jacobian(leg, length, ra)))

        good = conv & (cond < SINGULAR_COND) & (mode(P) == home_sign) & np.all(L > 0, axis=1)
        retry = np.flatnonzero(~good & np.all(L > 0, axis=1))
        if retry.size:
            # continuation: walk the legs from home to the target, Newton at each step
            L_home = self._gs_ik_platform(home[None], g)[2][0]
            Pc = np.broadcast_to(home, (retry.size, 4, 4)).copy()
            alive = np.ones(retry.size, dtype=bool)
            for s in np.linspace(0, 1, CONTINUATION_STEPS + 1)[1:]:
                Ls = L_home[None] + s * (L[retry] - L_home[None])
                Pn, c, _, cn, _ = self._gs_newton(Ls, Pc, g)
                ok_step = c & (cn < SINGULAR_COND) & (mode(Pn) == home_sign)
                alive &= ok_step
                Pc = np.where(alive[:, None, None], Pn, Pc)
            Pr, cr, rr, condr, _ = self._gs_newton(L[retry], Pc, g)
            fine = alive & cr & (condr < SINGULAR_COND) & (mode(Pr) == home_sign)
            P[retry[fine]] = Pr[fine]
            good[retry[fine]] = True
            res[retry], cond[retry] = np.where(fine, rr, res[retry]), np.where(fine, condr, cond[retry])
        reason = [""] * N
        for i in np.flatnonzero(~good):
            if np.any(L[i] <= 0):
                reason[i] = "a leg length is not positive"
            elif np.isfinite(cond[i]) and cond[i] >= SINGULAR_COND and res[i] < 1e-6:
                reason[i] = f"singular configuration (condition number {cond[i]:.3g})"
            else:
                reason[i] = "the legs cannot be assembled in the home assembly mode (outside the workspace)"
        T = P @ tool
        T[~good] = np.nan
        return FKResult(T, good, reason, it)

    # ---- Jacobians ----------------------------------------------------------------------------
    def jacobians(self, q, params=None, guess=None):
        """``(T, Jq, Jp)`` as :meth:`Model.jacobians`: tool poses ``(N,4,4)``, ``Jq (N,6,n)`` = d(tool
        position, world angular velocity)/d(actuators), ``Jp (N,6,P)`` = the same w.r.t. every parameter
        at fixed actuator values. Analytic: the inverse of the (closed-form) inverse-kinematics Jacobian."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        p = self.params if params is None else np.asarray(params, dtype=float)
        T = self.fk(q, p, guess).reshape(-1, 4, 4)
        N, n, P = len(q), self.n_joints, len(self.param_names)
        g = self.geometry(p)
        Jq = np.zeros((N, 6, n))
        Jp = np.zeros((N, 6, P))
        if self.type == PLANAR_STRUTS:
            c = g["pivots"]
            d = T[:, None, :2, 3] - c[None]
            u = d / np.linalg.norm(d, axis=2)[..., None]  # (N,2,2) rows: strut k direction
            Jinv = np.linalg.inv(u)  # d hinge / d lengths
            Jq[:, :2, :] = Jinv
            G = np.zeros((N, 2, P))  # d(lengths minus offsets)/d(params) at a fixed hinge
            for k in range(2):
                G[:, k, 2 * k:2 * k + 2] = -u[:, k]
                G[:, k, 4 + k] = -1.0
            Jp[:, :2, :] = -Jinv @ G
            return T, Jq, Jp
        Pl = T @ se3.invert(g["tool"])
        _, leg, length, ra = self._gs_ik_platform(Pl, g)
        u = leg / length[..., None]
        r_tool = T[:, :3, 3] - Pl[:, :3, 3]
        # d lengths / d tool twist: u . v_tool + ((r_anchor - r_tool) x u) . w
        Jik = np.concatenate([u, np.cross(ra - r_tool[:, None, :], u)], axis=2)
        Jinv = np.linalg.inv(Jik)
        Jq[:] = Jinv
        G = np.zeros((N, 6, 42))
        R = Pl[:, :3, :3]
        for k in range(6):
            G[:, k, 3 * k:3 * k + 3] = -u[:, k]  # base anchor k
            G[:, k, 18 + 3 * k:18 + 3 * k + 3] = np.einsum("nji,nj->ni", R, u[:, k])  # platform anchor k
            G[:, k, 36 + k] = -1.0  # leg offset
        Jp[:, :, :42] = -Jinv @ G
        # the tool frame moves the tool with the platform fixed: Tx Ty Tz Rz Ry Rx after the platform
        t = dict(zip(TCP_KEYS, p[42:48], strict=True))
        Jp[:, :3, 42:45] = R
        Rz = se3.rot_z(t["rz"])
        Ry = se3.rot_y(t["ry"])
        Jp[:, 3:, 45] = R @ np.array([0.0, 0.0, 1.0])
        Jp[:, 3:, 46] = R @ (Rz @ np.array([0.0, 1.0, 0.0]))
        Jp[:, 3:, 47] = R @ (Rz @ Ry @ np.array([1.0, 0.0, 0.0]))
        return T, Jq, Jp

    def jacobian_q(self, q, params=None) -> np.ndarray:
        return self.jacobians(q, params)[1]


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _step(P: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Platform poses moved by twists ``d (N,6)`` = [dp, dw] (world frame)."""
    out = P.copy()
    out[:, :3, 3] += d[:, :3]
    out[:, :3, :3] = se3.rotvec_to_matrix(d[:, 3:]) @ P[:, :3, :3]
    return out


# ---- builders ---------------------------------------------------------------------------------
def gough_stewart(name: str, base_anchors, platform_anchors, limits, home, *, tool=None, offsets=None,
                  description: str = "", max_velocity: float = 0.05, max_acceleration: float = 0.5,
                  encoder=None) -> ParallelModel:
    """A 6-6 Gough-Stewart platform (SI). ``limits``: one ``(lo, hi)`` or six; ``home``: platform pose
    ``x, y, z, rx, ry, rz`` (fixed-axis rpy); ``tool``: ``{x, y, z, rx, ry, rz}`` on the platform."""
    b = np.asarray(base_anchors, dtype=float).reshape(6, 3)
    a = np.asarray(platform_anchors, dtype=float).reshape(6, 3)
    lim = np.broadcast_to(np.asarray(limits, dtype=float), (6, 2))
    off = np.zeros(6) if offsets is None else np.asarray(offsets, dtype=float).reshape(6)
    tool = tool or {}
    joints = tuple(Joint(f"leg{k + 1}", "prismatic", float(lim[k, 0]), float(lim[k, 1]), max_velocity,
                         max_acceleration, encoder) for k in range(6))
    names: list[str] = []
    values: list[float] = []
    for side, pts in (("base", b), ("platform", a)):
        for k in range(6):
            for ax in range(3):
                names.append(f"anchor.{side}.{k + 1}.{'xyz'[ax]}")
                values.append(float(pts[k, ax]))
    names += [f"leg.{k + 1}.offset" for k in range(6)]
    values += [float(x) for x in off]
    names += [f"tcp.{k}" for k in TCP_KEYS]
    values += [float(tool.get(k, 0.0)) for k in TCP_KEYS]
    anchors = tuple(n for n in names if n.startswith("anchor."))
    groups = {"offsets": tuple(f"leg.{k + 1}.offset" for k in range(6)), "anchors": anchors,
              "base_anchors": anchors[:18], "platform_anchors": anchors[18:], "dh": anchors, "links": anchors,
              "tcp": ("tcp.x", "tcp.y", "tcp.z"), "tcp6": tuple(f"tcp.{k}" for k in TCP_KEYS)}
    return ParallelModel(name, GOUGH_STEWART, joints, tuple(names), np.array(values), groups, description,
                         np.asarray(home, dtype=float).reshape(6), 1)


def planar_struts(name: str, pivots, limits, branch: int = 1, *, offsets=None, description: str = "",
                  max_velocity: float = 0.05, max_acceleration: float = 0.5, encoder=None) -> ParallelModel:
    """The seed's planar robot: two length-variable struts on fixed pivots joined at one hinge (SI)."""
    c = np.asarray(pivots, dtype=float).reshape(2, 2)
    lim = np.broadcast_to(np.asarray(limits, dtype=float), (2, 2))
    off = np.zeros(2) if offsets is None else np.asarray(offsets, dtype=float).reshape(2)
    joints = tuple(Joint(f"strut{k + 1}", "prismatic", float(lim[k, 0]), float(lim[k, 1]), max_velocity,
                         max_acceleration, encoder) for k in range(2))
    names = [f"pivot.{k + 1}.{ax}" for k in range(2) for ax in "xy"] + [f"strut.{k + 1}.offset" for k in range(2)]
    values = [float(x) for x in c.reshape(-1)] + [float(x) for x in off]
    pivots_g = tuple(names[:4])
    groups = {"offsets": ("strut.1.offset", "strut.2.offset"), "pivots": pivots_g, "dh": pivots_g,
              "links": pivots_g, "tcp": (), "tcp6": ()}
    return ParallelModel(name, PLANAR_STRUTS, joints, tuple(names), np.array(values), groups, description,
                         None, int(branch))
