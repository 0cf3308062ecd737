"""Where a DYNAMIXEL arm may have a servo's torque off for an EEPROM write (Homing Offset) without dropping.

A DYNAMIXEL servo has no brake: with Torque Enable = 0 its horn is free (e-Manual, Torque Enable), and its
EEPROM area is writable only then. A joint whose gravity torque is below what its gear train holds by friction
stays where it is for the few milliseconds of the write; any other joint falls. The write-back therefore writes
one servo at a time while the others hold, and only where every joint to be written carries (almost) no gravity
torque: a vertical axis always, a horizontal one where the centre of mass beyond it stands straight above or
below it.

Finding that pose is done by measurement, as a technician would with the servo's own current reading, so that it
holds for the arm as built (link masses, a tool, cables) and not only for the model:
1. a first guess from the model's geometry: the links beyond each loaded joint straight up over its axis;
2. then Newton steps on the measured holding torques (Present Current): the gravity stiffness is probed by
   moving each loaded joint a few degrees (one move per joint), then steps of ``-J^-1 tau`` (re-probing when a
   step does not halve the torque);
3. within a few units of the current reading (its resolution, 2.69 mA on an XM430) the reading is too coarse
   for full Newton steps: damped ones in whole encoder ticks, halved each time the readings all change sign,
   until every joint to be written holds less than the hold torque.
Each pose is returned to the caller, which takes the arm there along its collision-checked route; the servos
never move on their own here."""

from __future__ import annotations

import math

import numpy as np

from station.kinematics.chain import forward, forward_marked, fuse_marked

PROBE = math.radians(4.0)  # rad: probe step of the gravity stiffness
MAX_STEP = math.radians(25.0)  # rad: largest Newton step per joint
LIMIT_MARGIN = math.radians(3.0)  # rad: targets stay this far inside the joint limits
MAX_MOVES = 40  # probes + steps before giving up
FINE = 3  # units of the torque reading: below this, tick steps instead of Newton steps
VERTICAL = math.cos(math.radians(2.0))  # |axis . z| above this: a vertical axis, gravity never loads it


def _frames(model, q: np.ndarray, program=None) -> np.ndarray:
    """Link frames (n + 1, 4, 4) at ``q``: links 1..n and the tool."""
    program = program or fuse_marked(model.chain, model.params, model.frames)
    T, F = forward_marked(program, np.atleast_2d(np.asarray(q, dtype=float)))
    return np.concatenate([F, T[:, None]], axis=1)[0]


def _axes(model, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per joint: its axis direction and a point on it ``(n, 3)`` each, base frame, at ``q``."""
    _, prefix = forward(model.chain, np.atleast_2d(np.asarray(q, float)), model.params, keep_prefix=True)
    mv = np.flatnonzero(model.chain.joint >= 0)
    e = mv[np.argsort(model.chain.joint[mv])]  # the chain element of each joint
    w = np.array([prefix[0, k, :3, int(model.chain.axis[k]) % 3] for k in e])
    return w, prefix[0, e, :3, 3]


def loadable(model, q: np.ndarray) -> list[bool]:
    """Per joint: can gravity load it here (a revolute joint whose axis is not vertical, a prismatic one whose
    axis is not horizontal)? Gravity is -z in the model's base frame."""
    w, _ = _axes(model, q)
    return [abs(float(a[2])) < VERTICAL if j.revolute else abs(float(a[2])) > 1 - VERTICAL
            for a, j in zip(w, model.joints, strict=True)]


def upright_guess(model, q: np.ndarray, joints: list[int], free: list[int]) -> np.ndarray:
    """A pose near ``q``, moving the joints ``free``, where the link-frame origins beyond each of ``joints`` (and
    the tool) stand straight over the joint's axis: no gravity torque whatever the masses along the links (model
    geometry; the arm as built differs, the measured Newton steps finish the job)."""
    q = np.asarray(q, dtype=float).copy()
    lo, hi = model.lower + LIMIT_MARGIN, model.upper - LIMIT_MARGIN
    program = fuse_marked(model.chain, model.params, model.frames)
    free = sorted(free)

    def residual(x):
        qq = q.copy()
        qq[free] = x
        F = _frames(model, qq, program)
        axes, points = _axes(model, qq)
        r = []
        for j in joints:
            o = points[j]
            h = np.cross(axes[j], [0.0, 0.0, 1.0])  # horizontal, perpendicular to the axis
            if np.linalg.norm(h) < 1e-9:
                continue
            h /= np.linalg.norm(h)
            for m in range(j, model.n_joints + 1):
                d = F[m, :3, 3] - o
                r.append(float(h @ d))
                r.append(min(0.0, float(d[2])))  # above the axis, not hanging below it: the arm high, clear
        r.extend(0.05 * (x - q[free]))  # stay near: of the many upright poses, the closest one
        return np.array(r)

    x = q[free].copy()
    for _ in range(30):  # Gauss-Newton, numeric Jacobian (a handful of joints)
        r = residual(x)
        J = np.empty((len(r), len(x)))
        for c in range(len(x)):
            d = np.zeros(len(x))
            d[c] = 1e-6
            J[:, c] = (residual(x + d) - r) / 1e-6
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        step = np.clip(step, -0.5, 0.5)
        x = np.clip(x + step, lo[free], hi[free])
        if np.max(np.abs(step)) < 1e-7:
            break
    out = q.copy()
    out[free] = x
    return out


class Balancer:
    """Measured Newton steps to a pose where ``joints`` hold less than ``hold`` N m, moving the joints ``free``
    (those whose position changes gravity's torque on them: a joint beyond its reach can be unloaded by the ones
    before it; least-norm steps when there are more of them): feed it the pose and the measured holding torques
    (N m) of ``joints``; it answers the next pose to go to, or None when balanced."""

    def __init__(self, lower: np.ndarray, upper: np.ndarray, joints: list[int], free: list[int], hold: float,
                 unit: np.ndarray, tick: np.ndarray) -> None:
        """``unit``: N m per unit of each joint's torque reading; ``tick``: rad per encoder tick of each joint
        (both for every joint of the arm)."""
        self.lo = np.asarray(lower, float) + LIMIT_MARGIN
        self.hi = np.asarray(upper, float) - LIMIT_MARGIN
        self.joints = list(joints)
        self.free = sorted(free)
        self.hold = float(hold)
        self.unit = np.asarray(unit, float)[self.joints]
        self.tick = np.asarray(tick, float)[self.free]
        self.moves = 0
        self._base: tuple[np.ndarray, np.ndarray] | None = None  # (pose, torque) the probes started from
        self._probes: list[np.ndarray] = []  # torque at each probe
        self._deltas: list[float] = []
        self._J: np.ndarray | None = None
        self._last: float | None = None  # |torque| before the last Newton step
        self._fine_sign: np.ndarray | None = None  # reading signs at the last fine step
        self._fine_gain = 0.5

    def balanced(self, tau: np.ndarray) -> bool:
        return bool(np.all(np.abs(tau) <= self.hold))

    def next_pose(self, q: np.ndarray, tau: np.ndarray) -> np.ndarray | None:
        q, tau = np.asarray(q, float), np.asarray(tau, float)
        if self.balanced(tau):
            return None
        if self.moves >= MAX_MOVES:
            raise RuntimeError(f"no pose found within {MAX_MOVES} moves where the joints to be written hold less "
                               f"than {self.hold:g} N m (still {np.max(np.abs(tau)):.3g} N m)")
        self.moves += 1
        fine = bool(np.all(np.abs(tau) <= FINE * self.unit))
        if self._J is not None and fine:
            return self._tick_step(q, tau)
        if self._J is not None and self._last is not None and np.max(np.abs(tau)) > 0.5 * self._last:
            self._J = None  # the step did not halve the torque: probe the stiffness again here
        if self._J is None:
            if self._base is None:
                self._base, self._probes, self._deltas = (q.copy(), tau.copy()), [], []
            else:
                self._probes.append(tau.copy())
            k = len(self._probes)
            if k < len(self.free):
                j = self.free[k]
                d = PROBE if q[j] + PROBE <= self.hi[j] else -PROBE
                self._deltas.append(d)
                target = self._base[0].copy()
                target[j] += d
                return target
            base_q, base_tau = self._base
            self._J = np.column_stack([(p - base_tau) / d for p, d in zip(self._probes, self._deltas, strict=True)])
            self._base = None
            q, tau = base_q, base_tau
        self._last = float(np.max(np.abs(tau)))
        if np.linalg.matrix_rank(self._J, tol=1e-9) < len(self.joints):
            raise RuntimeError("the joints' holding torques do not change with their position (a joint gravity "
                               "loads whatever its angle?)")
        step = np.clip(np.linalg.pinv(self._J) @ -tau, -MAX_STEP, MAX_STEP)
        target = q.copy()
        target[self.free] = np.clip(q[self.free] + step, self.lo[self.free], self.hi[self.free])
        return target

    def _tick_step(self, q: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Near zero the reading is coarser than the joints' resolution: a damped Newton step in whole ticks (at
        least one on the joint reading most), halved again whenever every reading changed sign since the last
        step (it went past the zero)."""
        sign = np.sign(tau)
        if self._fine_sign is not None and np.all(sign * self._fine_sign < 0):
            self._fine_gain *= 0.5
        self._fine_sign = sign
        ticks = self._fine_gain * (np.linalg.pinv(self._J) @ -tau) / self.tick
        n = np.round(ticks)
        if not n.any():  # at least one tick, on the joint that moves the readings most
            m = int(np.argmax(np.abs(ticks)))
            n[m] = math.copysign(1.0, ticks[m])
        target = q.copy()
        target[self.free] = np.clip(q[self.free] + n * self.tick, self.lo[self.free], self.hi[self.free])
        return target
