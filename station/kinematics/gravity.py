"""Gravity load on the joints: link masses, a tool payload, and the joint torques they cause.

A model with a :class:`Load` bends under gravity: revolute joint i turns by ``c_i * tau_i(q)`` where
``c_i = compliance.jN`` (rad per N*m) and ``tau_i`` is the gravity torque about joint i's axis, positive in
the joint's positive direction (the torque gravity *applies* to the joint, ``tau = -dV/dtheta`` with V the
potential energy), so a positive compliance lets the arm sag downwards.

First order, on a fixed geometry: ``tau`` is evaluated at the undeflected joint values ``q + offset`` on the
geometry frozen in the load (the model's parameters when the masses were attached, i.e. the nominal ones).
The deflection does not feed back into its own torque, and a calibration of the geometry does not change the
torques: both effects are of second order (compliance x geometry error, compliance^2 x torque; for
c = 1e-5 rad/N*m and 50 N*m they move the tool by well under a micrometre). It keeps the tool position an
exact, cheap function of q and the parameters, with compliance entering linearly in the joint values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.kinematics.chain import Chain, forward

STANDARD_GRAVITY = (0.0, 0.0, -9.81)  # m/s^2, in the model's base frame (z up)


@dataclass(frozen=True)
class Load:
    """Point masses fixed to the links (``link`` k = 1..n: the body joint k moves, in that link's frame;
    ``link`` n+1: the tool frame) and the gravity vector in the model's base (reference) frame."""

    gravity: np.ndarray  # (3,) m/s^2
    link: np.ndarray  # (M,) int
    mass: np.ndarray  # (M,) kg
    com: np.ndarray  # (M, 3) m, in the frame of ``link``
    params: np.ndarray  # the geometry (model parameter vector) the torques are computed on
    tool_link: int  # n + 1

    @property
    def payload(self) -> tuple[float, np.ndarray]:
        """Mass (kg) and centre of mass (m, tool frame) at the tool; (0, 0) when none."""
        return self._one(self.link == self.tool_link)

    def _one(self, sel: np.ndarray) -> tuple[float, np.ndarray]:
        if not sel.any():
            return 0.0, np.zeros(3)
        m = float(self.mass[sel].sum())
        com = (self.mass[sel] @ self.com[sel]) / m if m > 0 else np.zeros(3)
        return m, com

    def link_mass(self, k: int) -> tuple[float, np.ndarray]:
        """Mass (kg) and centre of mass (m, link frame) of link k (1-based)."""
        return self._one(self.link == k)


def make_load(n_links: int, params: np.ndarray, masses: dict[int, tuple[float, np.ndarray]] | None = None,
              payload: tuple[float, np.ndarray] | None = None, gravity=None) -> Load | None:
    """A load from per-link ``{k: (mass, com)}`` (k = 1..n), a payload ``(mass, com in the tool frame)``;
    None when there is no mass at all (a rigid, weightless model)."""
    links, ms, coms = [], [], []
    items = [(k, m, c, f"link {k}") for k, (m, c) in sorted((masses or {}).items())]
    if payload is not None:
        items.append((n_links + 1, payload[0], payload[1], "payload"))
    for k, m, c, what in items:
        c = np.asarray(c, dtype=float)
        if not 1 <= k <= n_links + 1:
            raise ValueError(f"mass of link {k}: the links are 1..{n_links}")
        if not (np.isfinite(m) and m >= 0) or c.shape != (3,) or not np.isfinite(c).all():
            raise ValueError(f"{what}: mass {m!r} kg at {c.tolist()!r}: need a finite mass >= 0 and a finite "
                             f"[x, y, z]")
        if m > 0:
            links.append(k), ms.append(float(m)), coms.append(c)
    g = np.asarray(STANDARD_GRAVITY if gravity is None else gravity, dtype=float)
    if not ms:
        return None
    return Load(g, np.array(links, dtype=int), np.array(ms), np.array(coms).reshape(-1, 3),
                np.asarray(params, dtype=float).copy(), n_links + 1)


def with_payload(load: Load | None, n_links: int, params: np.ndarray, mass: float, com=(0.0, 0.0, 0.0),
                 gravity=None) -> Load | None:
    """``load`` with its payload replaced (mass 0 removes it)."""
    masses = {} if load is None else {k: load.link_mass(k) for k in range(1, n_links + 1)}
    g = gravity if gravity is not None else (None if load is None else load.gravity)
    base = params if load is None else load.params
    return make_load(n_links, base, masses, (float(mass), np.asarray(com, dtype=float)), g)


def torques(chain: Chain, frames: np.ndarray, load: Load, q: np.ndarray, derivative: bool = False):
    """Gravity torque on every joint ``(N, n)`` (N*m for revolute joints, N along the axis for prismatic
    ones) at encoder values ``q (N, n)``, on the load's frozen geometry; with ``derivative`` also
    ``d tau_i / d q_j`` ``(N, n, n)`` (the gravity stiffness; exact for this point-mass model).

    ``frames[k-1]`` is the chain element after which link k's frame sits. For joint i (axis w_i through
    o_i) and the masses distal to it (total m_i, first moment mu_i = sum m p):
    ``tau_i = w_i . ((mu_i - m_i o_i) x g)`` (revolute) or ``w_i . (m_i g)`` (prismatic)."""
    q = np.atleast_2d(q)
    N, n = q.shape
    T, prefix = forward(chain, q, load.params, keep_prefix=True)
    K = chain.n_elements
    mv = np.flatnonzero(chain.joint >= 0)
    e = mv[np.argsort(chain.joint[mv])]  # element of joint i
    rev = chain.axis[e] >= 3
    elem = np.array([frames[k - 1] if k <= n else K - 1 for k in load.link], dtype=int)
    # frame after element k: prefix[:, k + 1], or the tool frame T after the last one
    F = np.where((elem + 1 < K)[None, :, None, None], prefix[:, np.minimum(elem + 1, K - 1)], T[:, None])
    p = np.einsum("nmij,mj->nmi", F[..., :3, :3], load.com) + F[..., :3, 3]  # (N, M, 3) mass positions
    w = prefix[:, e, :3, :][np.arange(N)[:, None], np.arange(n)[None, :], :, chain.axis[e] % 3]  # (N, n, 3)
    o = prefix[:, e][:, :, :3, 3]
    distal = (elem[None, :] >= e[:, None]) * load.mass[None, :]  # (n, M): mass m moves with joint i
    mt = distal.sum(axis=1)  # (n,)
    v = np.einsum("im,nmk->nik", distal, p) - mt[None, :, None] * o  # mu_i - m_i o_i
    g = load.gravity
    vxg = np.cross(v, g)
    tau = np.where(rev[None, :], np.einsum("nik,nik->ni", w, vxg), (w @ g) * mt[None, :])
    if not derivative:
        return tau
    # joint j moves the masses distal to it: revolute dp = w_j x (p - o_j), prismatic dp = w_j
    A = np.where(rev[None, :, None], np.cross(w, v), mt[None, :, None] * w)  # d(first moment)/d q_j
    upper = np.einsum("nik,njk->nij", w, np.cross(A, g))  # j at or after i: w_i . (A_j x g)
    # j before i (revolute): the whole subtree of i turns rigidly about w_j: g . (w_j x (w_i x v_i))
    lower = np.einsum("nik,njk->nij", np.cross(w, v), np.cross(g, w))
    jj, ii = np.meshgrid(np.arange(n), np.arange(n))  # [i, j]
    after = e[jj] >= e[ii]
    dtau = np.where(after[None], upper, np.where(rev[jj][None], lower, 0.0))
    if (~rev).any():  # a prismatic joint's force only turns with the joints before it: m_i g . (w_j x w_i)
        C = np.cross(w[:, None, :, :], w[:, :, None, :])  # C[:, i, j] = w_j x w_i
        turn = np.einsum("k,nijk->nij", g, C) * mt[None, :, None]
        dtau = np.where((~rev)[None, :, None], np.where(~after[None] & rev[jj][None], turn, 0.0), dtau)
    return tau, dtau


PAYLOAD_MASS_TOL = 1e-3  # kg: one gram
PAYLOAD_COM_TOL = 1e-4  # m: 0.1 mm


def payload_dict(model) -> dict | None:
    """The payload a model carries as files record it, ``{"mass": kg, "com": [x, y, z] m in the tool frame}``,
    or None without one (no gravity load, or mass 0)."""
    load = getattr(model, "load", None)
    if load is None:
        return None
    mass, com = load.payload
    return {"mass": float(mass), "com": [float(c) for c in com]} if mass > 0 else None


def same_payload(a: dict | None, b: dict | None) -> bool:
    """Two recorded payloads (``payload_dict`` shape, None or mass 0 for none) are the same load: mass to 1 g,
    centre of mass to 0.1 mm. A compliance term, or a sample, measured under one load belongs to it."""
    def parts(p):
        if p is None or float(p.get("mass", 0.0)) == 0.0:
            return 0.0, (0.0, 0.0, 0.0)
        return float(p["mass"]), tuple(float(c) for c in p["com"])

    try:
        (ma, ca), (mb, cb) = parts(a), parts(b)
    except (KeyError, TypeError, ValueError, AttributeError):
        return False
    return (abs(ma - mb) <= PAYLOAD_MASS_TOL and len(ca) == len(cb) == 3
            and all(abs(x - y) <= PAYLOAD_COM_TOL for x, y in zip(ca, cb, strict=True)))


def show_payload(p: dict | None) -> str:
    """``15 kg at [0, 0, 30] mm``, or ``no payload``."""
    if p is None or not float(p.get("mass", 0.0)):
        return "no payload"
    return f"{float(p['mass']):g} kg at [{', '.join(f'{float(c) * 1e3:g}' for c in p['com'])}] mm"
