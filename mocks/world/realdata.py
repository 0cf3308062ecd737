"""A simulated version of the real-data benchmark (docs/solver.md, real data): a 7-DOF arm with a ball tool seats the
ball in two sockets a known distance apart, ~30 times per socket in varied arm configurations, at several
positions of the fixture; its joints bend under the links' weight (hidden joint compliance).

The truth is the world's (``World``): hidden geometric errors drawn from its priors, link masses from the
model (URDF ``<inertial>``), joint compliance in ``joints.compliance``. A seated touch puts the TRUE ball
centre on the socket centre plus seating noise (the ball never sits exactly alike twice): the true joint
angles come from IK of the true, rigid geometry, and the encoders read ``q = theta - C tau(theta)`` (the
joints balance gravity at theta), checked against the world's own deflection."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from station.mocks.world.world import World

SOCKET_SPACING = 0.05  # m between the two sockets of the fixture
# hidden errors of a "real" arm (SI): joint zeros a few hundredths of a degree, link geometry a few tenths of a
# mm and hundredths of a degree, the ball's position on the hand half a millimetre
SIGMAS = {"offsets": {"length": 1e-4, "angle": 3e-4}, "dh": {"length": 3e-4, "angle": 3e-4},
          "tcp": {"length": 5e-4}}
COMPLIANCE = {2: (1.0e-5, 2.5e-5), 4: (1.0e-5, 3.0e-5), 6: (2e-5, 6e-5)}  # joint -> rad/(N m) range drawn from


@dataclass
class Touches:
    """Encoder readings of seated touches: ``q`` (N, n) SI, ``point`` (N,) socket labels A/B, ``fixture``
    (N,) position labels "1", "2", ...; ``centres`` the true socket centres per fixture position."""

    q: np.ndarray
    point: np.ndarray
    fixture: np.ndarray
    centres: dict[str, dict[str, np.ndarray]]

    def where(self, fixture: str) -> np.ndarray:
        return self.fixture == fixture


def arm_world(model_path: str, seed: int, tip_link: str = "ball") -> World:
    """A simulated arm of the benchmark: the model's geometry with errors drawn from ``SIGMAS`` and joint
    compliance drawn from ``COMPLIANCE`` (seeded: robot ``seed`` is always the same robot)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 11]))
    compliance = {f"j{j}": float(rng.uniform(lo, hi)) for j, (lo, hi) in COMPLIANCE.items()}
    return World.default("ur5e", seed=seed, robot={"model": str(model_path), "tip_link": tip_link},
                         errors={"random": SIGMAS}, joints={"compliance": compliance}, cell={"points": []})


def fixture_positions(n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` fixture poses (socket A's centre, unit direction from A to B) spread over the front of the arm's
    workspace, on a table 0.1-0.3 m above the base, turned at random about the vertical."""
    out = []
    for k in range(n):
        ang = -0.9 + 1.8 * (k + rng.uniform(0.2, 0.8)) / n  # spread around the base, not all in one place
        r = rng.uniform(0.45, 0.6)
        c = np.array([r * np.cos(ang), r * np.sin(ang), rng.uniform(0.1, 0.3)])
        yaw = rng.uniform(-np.pi, np.pi)
        out.append((c, np.array([np.cos(yaw), np.sin(yaw), 0.0])))
    return out


def seated_touches(world: World, centres: dict[str, np.ndarray], n: int, rng: np.random.Generator,
                   noise: float) -> tuple[np.ndarray, list[str]]:
    """``n`` touches per socket: varied configurations (IK from random seeds within the joint limits), the
    true ball centre ``noise`` (m per axis) off the socket centre, and the encoder readings of the deflected
    arm."""
    truth, grav = world.truth, world.gravity
    lo, hi = truth.lower, truth.upper
    qs, labels = [], []
    for label, c in centres.items():
        got = 0
        for _ in range(200):
            if got >= n:
                break
            m = max(2 * (n - got), 8)
            seeds = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(m, truth.n_joints))
            target = c + rng.normal(0.0, noise, size=(m, 3))
            res = truth.ik(target, seeds, tol_pos=1e-10, max_iter=300)
            ok = res.ok & (res.position_error < 1e-9) & np.all((res.q > lo) & (res.q < hi), axis=1)
            for theta in res.q[ok][: n - got]:
                # the springs balance gravity at theta: theta = q + C tau(theta), exactly
                qs.append(theta - grav.compliance * grav.torque(theta) if grav.active else theta.copy())
                labels.append(label)
                got += 1
        if got < n:
            raise RuntimeError(f"socket {label} at {c}: only {got} of {n} seated configurations found")
    return np.array(qs), labels


def two_socket_data(world: World, rng: np.random.Generator, positions: int = 4, per_socket: int = 30,
                    noise: float | None = None) -> Touches:
    """The data set of one arm: ``positions`` fixture positions, ``per_socket`` touches of each socket at
    each, seating noise ``noise`` (m per axis; default drawn in 0.05-0.1 mm)."""
    noise = float(rng.uniform(0.05e-3, 0.1e-3)) if noise is None else noise
    qs, pts, fx, centres = [], [], [], {}
    for k, (a, u) in enumerate(fixture_positions(positions, rng)):
        f = str(k + 1)
        centres[f] = {"A": a, "B": a + SOCKET_SPACING * u}
        q, lb = seated_touches(world, centres[f], per_socket, rng, noise)
        qs.append(q)
        pts += lb
        fx += [f] * len(lb)
    return Touches(np.vstack(qs), np.array(pts, dtype=object), np.array(fx, dtype=object), centres)


def consistency(P: np.ndarray, point: np.ndarray) -> float:
    """The held-out consistency error of predicted ball centres ``P`` (N, 3) of touches of sockets ``point``:
    for each socket, the mean distance of its touches' predicted positions from their centroid; the mean
    over the sockets (m). A perfect model predicts every touch of a socket at the same place."""
    out = []
    for lb in dict.fromkeys(point.tolist()):
        p = P[point == lb]
        out.append(float(np.mean(np.linalg.norm(p - p.mean(axis=0), axis=1))))
    return float(np.mean(out))
