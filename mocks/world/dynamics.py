"""Joints the controller does not hold rigidly: free-running, torque-commanded, or torque-limited.

Units SI: torques in N m (N for a prismatic joint), inertia in kg m^2 (kg), damping in N m s/rad (N s/m),
positions rad (m), velocities rad/s (m/s).

Most of the time every joint of the simulated robot follows its motion profile exactly (``motion.Track``):
a position-controlled servo or drive is stiff. Three states are not, and a real arm shows them:

- **free**: power or torque off and no brake on the joint (a DYNAMIXEL with Torque Enable = 0 is free-running;
  ROBOTIS e-Manual, "Torque Enable"): the joint moves under gravity until friction holds it or it reaches
  its end stop;
- **torque**: the drive commands a torque and nothing holds position (CiA 402 profile torque mode);
- **saturated**: position control whose torque limit (CiA 402 0x6072 / 0x60E0 / 0x60E1, a current limit) is
  below what holding the joint takes: the joint sags while the drive pushes its limit against gravity.

Gravity torque is minus the derivative of the potential energy on the TRUE geometry
(``physics.Gravity.torque``). A world without link masses (``joints.masses``, the model's ``mass``/``com``)
would let an unbraked joint float where a real one falls, so the dynamics then estimate masses from the
arm's size (:func:`estimated_masses`). The joints are integrated one by one with the diagonal of the
joint-space mass matrix (coupling between joints is neglected: an emulator needs the sag and its direction,
not a multibody simulation), with viscous damping (implicit, so stable at any step) and Coulomb friction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from station.mocks.world.physics import LinkFrames

STEP = 2e-3  # s of world time per integration step (the stiffest motion, a saturated controller, is ~60 rad/s)
MAX_STEPS = 4000  # per update: beyond that the steps grow (a long unobserved gap is integrated coarsely)
SETTLE_TIME = 10.0  # s: what instant mode integrates at most when a joint lets go
REST_SPEED = 1e-6  # rad/s (m/s): slower than this, and friction or the controller holding, a joint is at rest
KP_BANDWIDTH = 60.0  # rad/s: closed-loop bandwidth of a saturated position controller (stiff, as drives are)
L_UR5E = 1.15  # m: sum of the UR5e's link lengths (frame origin to frame origin) ...
M_UR5E = 16.0  # kg: ... and the mass its joints carry (20.6 kg arm less the base)
FALL_SPEED = 2.0  # rad/s: default damping lets a fully loaded joint fall at about this speed (a geared joint)
FRICTION = 0.01  # default Coulomb friction, as a share of the arm's largest gravity torque (gears always have some)


def estimated_masses(model) -> dict[int, tuple[float, np.ndarray]]:
    """Point masses ``{k: (kg, com in link k's frame)}`` for a model that states none: each link's mass at
    the middle of the segment to the next frame origin, in proportion to its length; the total scales with
    the cube of the arm's size from a UR5e (a 0.38 m arm carries about 0.6 kg, as a small servo arm does)."""
    theta = np.zeros((1, model.n_joints))
    F = LinkFrames(model)(theta)[0]
    origins = F[:, :3, 3]
    seg = np.linalg.norm(np.diff(origins, axis=0), axis=1)  # link k: origin k -> origin k+1 (tool for the last)
    total = float(seg.sum())
    if total <= 0:
        return {}
    mass = M_UR5E * (total / L_UR5E) ** 3
    out = {}
    for k in range(model.n_joints):
        if seg[k] <= 0:
            continue
        mid = 0.5 * (origins[k] + origins[k + 1])
        com = np.linalg.solve(F[k], np.r_[mid, 1.0])[:3]
        out[k + 1] = (mass * seg[k] / total, com)
    return out


@dataclass
class JointDynamicsSpec:
    """Per-joint constants of the world file's ``joints.dynamics`` (SI); None: the default below."""

    inertia: dict[int, float]  # added inertia at the joint (rotor through the gear), kg m^2
    damping: dict[int, float]  # viscous, N m s/rad
    friction: dict[int, float]  # Coulomb, N m


class Dynamics:
    """Integrates the joints that are not on a motion profile. ``gravity``: a ``physics.Gravity`` whose
    ``torque(theta)`` is the truth's (with estimated masses when the world states none)."""

    def __init__(self, model, gravity, spec: JointDynamicsSpec | None = None) -> None:
        self.model = model
        self.gravity = gravity
        n = model.n_joints
        spec = spec or JointDynamicsSpec({}, {}, {})
        scale = self._load_scale()
        self.rotor = np.array([spec.inertia.get(i, 0.05 * self._link_inertia_scale()) for i in range(n)])
        self.damping = np.array([spec.damping.get(i, max(scale, 1e-3) / FALL_SPEED) for i in range(n)])
        self.friction = np.array([spec.friction.get(i, FRICTION * scale) for i in range(n)])

    def _load_scale(self) -> float:
        """A torque typical of the arm's gravity load (N m): the largest gravity torque at zero."""
        tau = self.gravity.torque(np.zeros(self.model.n_joints))
        return float(np.abs(tau).max()) if tau.size else 0.0

    def _link_inertia_scale(self) -> float:
        m = float(self.gravity.mass.sum()) if self.gravity.mass.size else 0.0
        r = float(np.linalg.norm(self.gravity.com, axis=1).max()) if self.gravity.com.size else 0.1
        return max(m * r * r, 1e-5)

    def forces(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(gravity torque (n,), inertia (n,))`` at ``theta``: both from one batch of mass positions, the
        torque as ``sum m g . dp/dtheta`` (= -dV/dtheta), the inertia as the diagonal of the joint-space mass
        matrix of the point masses plus the rotor inertia."""
        n = len(theta)
        h = 1e-6
        E = np.eye(n) * h
        P = self.gravity.mass_positions(np.vstack([theta + E, theta - E]))  # (2n, masses, 3)
        dP = (P[:n] - P[n:]) / (2 * h)  # (n, masses, 3): d p_m / d theta_i
        tau = np.einsum("m,imk,k->i", self.gravity.mass, dP, self.gravity.g)
        inertia = np.einsum("m,imk,imk->i", self.gravity.mass, dP, dP) + self.rotor
        return tau, inertia

    def step(self, x: np.ndarray, v: np.ndarray, tau_motor: np.ndarray, dt: float, active: np.ndarray,
             lower: np.ndarray, upper: np.ndarray, tau_g: np.ndarray, inertia: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One step of ``dt`` for the ``active`` joints (the others are returned unchanged): semi-implicit
        Euler with the damping implicit (stable at any step), Coulomb friction that holds a joint at rest while
        the net torque is below it and never reverses it, end stops at the joint limits (velocity to zero).
        Returns ``(x, v, rest)``: ``rest`` marks active joints that stay where they are until a force changes."""
        net = tau_g + tau_motor
        x, v = x.copy(), v.copy()
        rest = np.zeros(len(x), dtype=bool)
        for i in np.flatnonzero(active):
            pushes_stop = (x[i] <= lower[i] and net[i] <= 0) or (x[i] >= upper[i] and net[i] >= 0)
            # at rest: slower than REST_SPEED, and what friction leaves of the torque could not drive it faster
            # than that against the damping
            held = abs(net[i]) <= self.friction[i] + REST_SPEED * self.damping[i]
            if abs(v[i]) < REST_SPEED and (held or pushes_stop):
                v[i], rest[i] = 0.0, True
                continue
            moving = abs(v[i]) >= REST_SPEED
            f = net[i] - math.copysign(self.friction[i], v[i] if moving else net[i])
            vn = (v[i] + dt * f / inertia[i]) / (1.0 + dt * self.damping[i] / inertia[i])
            if moving and vn * v[i] < 0 and abs(net[i]) <= self.friction[i]:
                vn = 0.0  # friction stops the joint; it does not drive it back
            xn = x[i] + dt * vn
            if xn <= lower[i] or xn >= upper[i]:  # the end stop
                xn, vn = float(np.clip(xn, lower[i], upper[i])), 0.0
            x[i], v[i] = xn, vn
        return x, v, rest

    def position_controller(self, x: np.ndarray, v: np.ndarray, x_ref: np.ndarray, v_ref: np.ndarray,
                            limit: np.ndarray, tau_g: np.ndarray, inertia: np.ndarray) -> np.ndarray:
        """Motor torque of a stiff position controller held to ``limit``. Its integrator cancels gravity and the
        friction it works against (a drive has no steady-state error it can still push away)."""
        w = KP_BANDWIDTH
        push = w * w * (x_ref - x) + 2 * w * (v_ref - v)
        tau = -tau_g + inertia * push + self.friction * np.sign(push)
        return np.clip(tau, -limit, limit)
