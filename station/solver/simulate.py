"""Simulated touch data for tests and benchmarks: joint readings that put the tip of a (true) model on
fixed points from many orientations, plus Gaussian touch noise. Pure; the hardware-level simulated world
lives in ``station.mocks``."""

from __future__ import annotations

import numpy as np

from station.solver.observations import Observations


def random_q(model, n: int, rng: np.random.Generator, spread: float = 1.0, centre=None) -> np.ndarray:
    """Joint values uniformly in ``centre +- spread * half range`` (clipped to a 'sane' window of
    +-pi around the centre for revolute joints with very wide limits)."""
    lo, hi = model.lower.copy(), model.upper.copy()
    rev = np.array([j.revolute for j in model.joints])
    c = (lo + hi) / 2 if centre is None else np.asarray(centre, dtype=float)
    half = np.minimum((hi - lo) / 2, np.where(rev, np.pi, np.inf))
    q = c + spread * half * rng.uniform(-1, 1, size=(n, model.n_joints))
    return np.clip(q, lo, hi)


def touch_q(model, point, n: int, rng: np.random.Generator, *, centre=None, spread: float = 0.8,
            max_tries: int = 40) -> np.ndarray:
    """``n`` joint configurations whose tool tip (of ``model``, i.e. the truth) is exactly on ``point``,
    from IK started at random seeds: the seeds' diversity gives diverse tool orientations."""
    point = np.asarray(point, dtype=float)
    out: list[np.ndarray] = []
    for _ in range(max_tries):
        seeds = random_q(model, max(2 * n, 8), rng, spread, centre)
        res = model.ik(np.broadcast_to(point, (len(seeds), 3)), seeds, tol_pos=1e-10, max_iter=300)
        out.extend(res.q[res.ok & (res.position_error < 1e-9)])
        if len(out) >= n:
            break
    if len(out) < n:
        raise RuntimeError(f"could only reach {point} from {len(out)} of {n} configurations")
    return np.array(out[:n])


def touch_observations(truth, points: dict[str, np.ndarray], n_per_point: int, rng: np.random.Generator, *,
                       noise: float = 20e-6, centre=None, spread: float = 0.8) -> Observations:
    """Touches of every point; noise is added to the tip position and mapped to joint readings through the
    joint Jacobian pseudo-inverse (the touch lands ``noise`` away from the point)."""
    qs, labels = [], []
    for label, p in points.items():
        q = touch_q(truth, p, n_per_point, rng, centre=centre, spread=spread)
        qs.append(q)
        labels += [label] * len(q)
    q = np.vstack(qs)
    targets = np.array([points[lb] for lb in labels], dtype=float)
    if noise > 0:
        q = noisy_q(truth, q, targets, noise, rng)
    return Observations(q, np.array(labels, dtype=object))


def noisy_q(truth, q: np.ndarray, targets: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Joint readings of touches that land ``N(0, noise^2 I)`` away from ``targets``: the tip error is
    drawn in space and mapped to the joints through the joint Jacobian pseudo-inverse, then one Newton
    correction puts the true tip exactly at ``target + dp``."""
    dp = rng.normal(0.0, noise, size=(len(q), 3))
    _, Jq, _ = truth.jacobians(q)
    q = q + np.einsum("nij,nj->ni", np.linalg.pinv(Jq[:, :3]), dp)
    P = truth.position(q)
    _, Jq, _ = truth.jacobians(q)
    return q + np.einsum("nij,nj->ni", np.linalg.pinv(Jq[:, :3]), targets + dp - P)
