"""Gravity on the simulated robot: the truth the station's compliance model is tested against.

Computed independently of ``station.kinematics.gravity``'s analytic torque formula: the torque on each joint
is minus the derivative of the potential energy ``V = -sum m g . p_m`` (central differences of the mass
positions on the TRUE geometry), and the deflection is the exact fixed point ``theta = q + C tau(theta)``
(the torque is evaluated where the joints really are), not the station's first-order model."""

from __future__ import annotations

import numpy as np

from station.kinematics.chain import forward_marked, fuse_marked

STEP = 1e-6  # rad (m for prismatic joints): central-difference step of the potential energy
FIXED_POINT_TOL = 1e-13  # rad


class LinkFrames:
    """Frames ``(N, n + 1, 4, 4)`` of links 1..n and of the tool at joint values ``theta (N, n)``: link k's
    frame is the one after element ``model.frames[k - 1]`` (it moves with joint k). The chain is fused once for
    the model's parameter vector (a few matrix products per configuration: the dynamics call this every ms)."""

    def __init__(self, model) -> None:
        self.program = fuse_marked(model.chain, model.params, model.frames)

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        T, frames = forward_marked(self.program, np.atleast_2d(theta))
        return np.concatenate([frames, T[:, None]], axis=1)


class Rigid:
    """No gravity deflection: parallel robots (their legs are axial actuators; the world models no sag)."""

    active = False
    masses: dict = {}
    payload = (0.0, np.zeros(3))

    def deflect(self, q: np.ndarray) -> np.ndarray:
        return q


class Gravity:
    """Point masses ``{k: (kg, com)}`` on links k = 1..n (com in the model's link frame k), a payload
    ``(kg, com in the tool frame)``, gravity (m/s^2, base frame) and per-joint compliance (rad/(N m), m/N
    for prismatic joints) on the rigid ``model``."""

    def __init__(self, model, masses: dict, payload: tuple, gravity, compliance: np.ndarray) -> None:
        self.model = model
        self.masses, self.payload = dict(masses), payload  # as given, for reports
        links = [(k, m, c) for k, (m, c) in sorted(masses.items()) if m > 0]
        if payload[0] > 0:
            links.append((model.n_joints + 1, payload[0], payload[1]))
        self.frames = LinkFrames(model)
        self.link = np.array([k - 1 for k, _, _ in links], dtype=int)  # index into link_frames(): n = the tool
        self.mass = np.array([m for _, m, _ in links], dtype=float)
        self.com = np.array([np.asarray(c, dtype=float) for _, _, c in links]).reshape(-1, 3)
        self.g = np.asarray(gravity, dtype=float)
        self.compliance = np.asarray(compliance, dtype=float)
        self.active = bool(self.compliance.any() and self.mass.sum() > 0 and self.g.any())

    def mass_positions(self, theta: np.ndarray) -> np.ndarray:
        """Positions ``(N, masses, 3)`` (m, base frame) of the point masses at joint values ``theta (N, n)``."""
        F = self.frames(theta)[:, self.link]
        return np.einsum("nmij,mj->nmi", F[..., :3, :3], self.com) + F[..., :3, 3]

    def potential(self, theta: np.ndarray) -> np.ndarray:
        """Potential energy (J) at joint values ``theta (N, n)``."""
        return -np.einsum("m,nmk,k->n", self.mass, self.mass_positions(theta), self.g)

    def torque(self, theta: np.ndarray) -> np.ndarray:
        """``-dV/dtheta`` ``(n,)`` at one configuration: the torque (force) gravity applies to each joint."""
        n = len(theta)
        E = np.eye(n) * STEP
        V = self.potential(np.vstack([theta + E, theta - E]))
        return -(V[:n] - V[n:]) / (2 * STEP)

    def deflect(self, q: np.ndarray) -> np.ndarray:
        """Joint values where the springs balance gravity: ``theta = q + C tau(theta)``."""
        if not self.active:
            return q
        theta = q.copy()
        for _ in range(20):
            new = q + self.compliance * self.torque(theta)
            done = np.abs(new - theta).max() < FIXED_POINT_TOL
            theta = new
            if done:
                break
        return theta
