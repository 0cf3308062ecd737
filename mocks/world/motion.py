"""One joint's motion as a list of constant-acceleration phases, evaluated lazily at any time.

A track starts at ``(t0, x0, v0)`` and runs through ``phases = [(duration, acceleration), ...]``; after
the last phase the joint rests. Planning is time-optimal per joint under a velocity and an acceleration
limit (trapezoid or triangle), also from a non-zero initial velocity, so a new goal can arrive while the
joint is moving without a velocity jump. The world synchronises joints by scaling each joint's limits."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

EPS = 1e-12


@dataclass
class Track:
    t0: float
    x0: float
    v0: float = 0.0
    phases: list[tuple[float, float]] = field(default_factory=list)
    side: float = 1.0  # direction of the last motion (backlash side) at t0

    @property
    def t_end(self) -> float:
        return self.t0 + sum(d for d, _ in self.phases)

    @property
    def x_end(self) -> float:
        return self.state(math.inf)[0]

    def state(self, t: float) -> tuple[float, float, float]:
        """``(position, velocity, side)`` at time ``t`` (before ``t0``: the start state)."""
        x, v, side = self.x0, self.v0, self.side
        if abs(v) > EPS:
            side = math.copysign(1.0, v)
        rest = max(0.0, t - self.t0)
        done = 0
        for dur, acc in self.phases:
            if rest <= 0.0:
                break
            dt = min(dur, rest)
            v_end = v + acc * dt
            x += v * dt + 0.5 * acc * dt * dt
            if abs(v_end) > EPS:
                side = math.copysign(1.0, v_end)
            v = v_end
            rest -= dt
            done += dt >= dur
        if done == len(self.phases):
            v = 0.0  # every track ends at rest; drop rounding residue
        return x, v, side


def hold(t: float, x: float, side: float = 1.0) -> Track:
    return Track(t, x, 0.0, [], side)


def plan(t0: float, x0: float, v0: float, x1: float, vmax: float, amax: float, side: float = 1.0) -> Track:
    """Time-optimal move from ``(x0, v0)`` to rest at ``x1`` with ``|v| <= vmax``, ``|a| <= amax``."""
    if vmax <= 0 or amax <= 0:
        raise ValueError(f"velocity and acceleration limits must be positive (got {vmax}, {amax})")
    phases = _phases(x0, v0, x1, vmax, amax)
    tr = Track(t0, x0, v0, phases, side)
    if not phases:
        tr.x0 = x1
    else:  # absorb rounding so that the track ends exactly on the target
        tr.x0 = x0 + (x1 - tr.x_end)
    return tr


def _phases(x0: float, v0: float, x1: float, vmax: float, amax: float) -> list[tuple[float, float]]:
    phases: list[tuple[float, float]] = []
    d = x1 - x0
    if abs(d) < EPS and abs(v0) < EPS:
        return phases
    s = math.copysign(1.0, d) if abs(d) > EPS else math.copysign(1.0, -v0)
    u0 = s * v0  # initial speed towards the target (negative: moving away)
    D = abs(d)
    stop = u0 * u0 / (2 * amax) if u0 > 0 else 0.0
    if u0 < 0 or stop > D + EPS:
        # moving away or cannot stop in time: brake to rest first, then plan again from rest
        a = -math.copysign(amax, v0)
        tb = abs(v0) / amax
        xb = x0 + v0 * tb + 0.5 * a * tb * tb
        return [(tb, a), *_phases(xb, 0.0, x1, vmax, amax)]
    if u0 > vmax:  # over the (new) speed limit: slow down to it first
        t1 = (u0 - vmax) / amax
        phases.append((t1, -s * amax))
        D -= (u0 * u0 - vmax * vmax) / (2 * amax)
        u0 = vmax
    vp = max(u0, min(vmax, math.sqrt(amax * D + 0.5 * u0 * u0)))
    t_acc = (vp - u0) / amax
    d_acc = (vp * vp - u0 * u0) / (2 * amax)
    d_dec = vp * vp / (2 * amax)
    t_cruise = max(0.0, (D - d_acc - d_dec) / vp) if vp > EPS else 0.0
    if t_acc > EPS:
        phases.append((t_acc, s * amax))
    if t_cruise > EPS:
        phases.append((t_cruise, 0.0))
    if vp > EPS:
        phases.append((vp / amax, -s * amax))
    return phases


def brake(t0: float, x0: float, v0: float, amax: float, side: float = 1.0) -> Track:
    """Decelerate to rest at ``amax``."""
    if abs(v0) < EPS:
        return Track(t0, x0, 0.0, [], side)
    return Track(t0, x0, v0, [(abs(v0) / amax, -math.copysign(amax, v0))], side)


def min_time(distance: float, vmax: float, amax: float) -> float:
    """Duration of a rest-to-rest move over ``distance``."""
    D = abs(distance)
    if D < EPS:
        return 0.0
    if D * amax <= vmax * vmax:  # triangle
        return 2.0 * math.sqrt(D / amax)
    return D / vmax + vmax / amax


def synchronised_limits(distances, vmax, amax) -> tuple[list[float], list[float]]:
    """Per-joint limits that make all joints of a rest-to-rest move finish together on a straight
    line in joint space: every joint follows ``x0 + d_i * s(t)`` with one trapezoid ``s`` whose limits
    are the tightest ``vmax_i/|d_i|``, ``amax_i/|d_i|`` over the moving joints."""
    moving = [i for i, d in enumerate(distances) if abs(d) > EPS]
    if not moving:
        return list(vmax), list(amax)
    vs = min(vmax[i] / abs(distances[i]) for i in moving)
    as_ = min(amax[i] / abs(distances[i]) for i in moving)
    v = [vs * abs(d) if abs(d) > EPS else vmax[i] for i, d in enumerate(distances)]
    a = [as_ * abs(d) if abs(d) > EPS else amax[i] for i, d in enumerate(distances)]
    return v, a
