"""The seating press: after a stiff approach, the Cartesian-impedance target goes on along the approach by
``force / stiffness``, so the arm presses with a known force and the socket's cone, not the controller, centres
the ball (how a ball or a peg is seated under impedance: approach position-controlled, switch to impedance,
push on with a set force; Franka documents the Cartesian impedance and the external force estimate the press
relies on, libfranka ``robot.h`` ``setCartesianImpedance`` and ``robot_state.h`` ``O_F_ext_hat_K``).

Pure computations (no robot I/O), used by ``drivers.franka.robot``: the direction, the joint target, and when the
pressed arm has come to rest. Units: m, rad, N, s."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

MIN_APPROACH = 1e-3  # m: a move whose tool travels less than this has no direction to press along
TRAVEL = 6e-3  # m: travel without contact the press may take beyond where the stiff move ended before it is
# called off (a socket's cone meets the ball within the approach error, under a millimetre once aimed; the
# two-socket procedure stands off 4 mm and its first aim at a socket is the cell's, good to a millimetre or two;
# more than this in free air means nothing is there to seat in)
WINDOW = 1.0  # s: the press follows a stiff move only when compliance is taken up this soon after it ended (a
# seating step does it at once; a technician who jogs and then turns compliance on by hand does not)
SPEED = 0.02  # m/s: the press target moves at this tool speed (a touch, not a blow)
REST_TOOL = 1e-3  # m/s: the pressed tool rests when slower than this ...
STEADY_S = 0.1  # s ... for this long, while the force along the press varies by less than
STEADY_FORCE = 1.0  # N (or a fifth of the press, whichever is more): the estimate's noise is ~0.2 N per axis


@dataclass(frozen=True)
class Press:
    """One press: the unit direction ``u`` at the tool (base frame), where it starts (``p0``, tool point, m) and
    the joint target ``q`` (``depth`` m beyond the start along ``u``, orientation kept)."""

    u: np.ndarray
    p0: np.ndarray
    q: np.ndarray
    depth: float

    def travel(self, p) -> float:
        """How far the tool at ``p`` has gone beyond the start along the press (m)."""
        return float((np.asarray(p, float) - self.p0) @ self.u)


def direction(model, q_from, q_to, q_now) -> tuple[np.ndarray | None, str]:
    """The unit direction to press along: the straight-line tool travel of the stiff move ``q_from`` ->
    ``q_to`` (the approach: for a socket, its axis as the procedure planned it), or ``None`` and why not (a
    rotation in place; a move that ended farther than ``TRAVEL`` from its target, e.g. stopped by something
    that is not the socket)."""
    p_from, p_to, p_now = (model.position(np.asarray(q, float)) for q in (q_from, q_to, q_now))
    dx = p_to - p_from
    n = float(np.linalg.norm(dx))
    if n < MIN_APPROACH:
        return None, f"the move travelled {n * 1e3:.2f} mm at the tool (a rotation in place)"
    off = float(np.linalg.norm(p_now - p_to))
    if off > TRAVEL:
        return None, f"the move ended {off * 1e3:.1f} mm from its target (stopped by something?)"
    return dx / n, ""


def plan(model, q_now, u, depth: float) -> Press:
    """The joint target ``depth`` m beyond the tool's pose at ``q_now`` along ``u``, orientation kept (three
    least-squares Jacobian steps: one alone misses by the second-order term, ~0.1 mm over 8 mm)."""
    q_now = np.asarray(q_now, float)
    T0 = model.fk(q_now)
    goal = T0[:3, 3] + np.asarray(u, float) * depth
    q = q_now.copy()
    for _ in range(3):
        T = model.fk(q)
        rot = 0.5 * sum(np.cross(T[:3, i], T0[:3, i]) for i in range(3))
        J = model.jacobian_q(q).reshape(6, -1)
        q = q + np.linalg.pinv(J) @ np.concatenate([goal - T[:3, 3], rot])
    return Press(u=np.asarray(u, float), p0=T0[:3, 3].copy(), q=q, depth=float(depth))


def joint_speed(press: Press, q_now) -> float:
    """The joint speed (rad/s, the joint that moves most) that moves the tool at ``SPEED``."""
    dq = float(np.max(np.abs(press.q - np.asarray(q_now, float))))
    return max(dq * SPEED / max(press.depth, 1e-9), 1e-4)


class Settle:
    """Rest after a press: the tool slower than ``REST_TOOL`` and the force along the press steady (within
    ``max(STEADY_FORCE, press_force / 5)``) for ``STEADY_S``. Feed it samples with ``add``; ``rested`` says so."""

    def __init__(self, press_force: float) -> None:
        self.band = max(STEADY_FORCE, press_force / 5)
        self._window: deque[tuple[float, float]] = deque()
        self._since: float | None = None

    def add(self, t: float, tool_speed: float, force_along: float) -> bool:
        if tool_speed > REST_TOOL:
            self._window.clear()
            self._since = None
            return False
        self._window.append((t, force_along))
        while self._window and t - self._window[0][0] > STEADY_S:
            self._window.popleft()
        forces = [f for _, f in self._window]
        if max(forces) - min(forces) > self.band:  # still changing: the rest starts over from this sample
            self._window.clear()
            self._window.append((t, force_along))
            self._since = t
        self._since = t if self._since is None else self._since
        return t - self._since >= STEADY_S

    @property
    def rested(self) -> bool:
        return self._since is not None and bool(self._window) and self._window[-1][0] - self._since >= STEADY_S
