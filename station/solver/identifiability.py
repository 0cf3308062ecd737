"""Which unknowns can the data identify? Column-scaled, priority-ordered rank revealing (Gram-Schmidt
with re-orthogonalisation, i.e. a QR factorisation with a chosen column order) plus an SVD for the
condition number and the observability index.

Columns are scaled to metres (angles times the characteristic length L), so a column's norm is how far
the tool moves, summed over the poses, per metre (or per L radians) of that parameter. Column j is
*dependent* when what remains of it after projecting out the columns accepted before it is below

    tau_j = max(rtol * max_k |J_k|,  sigma / max_std)

The first term catches exact redundancy (the model's deliberate over-parameterisation); the second one
is tied to the noise: with residual standard deviation sigma, the standard deviation of that parameter,
given the ones before it, would be sigma / |remainder| > max_std (default 1 mm at the tool)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg.lapack import dgeqrf, dpotrf, dpotrs, dsyev

RTOL = 1e-7
PRIORITY = ("point.", "instrument", "tcp.", "offset.", "base.")


@dataclass
class RankAnalysis:
    accepted: list[int]  # column indices the data identify, in acceptance order
    rejected: dict[int, str]  # column -> reason
    rank: int
    condition_number: float | None
    observability_index: float | None  # O1 = (s1 ... sr)^(1/r) / sqrt(m) of the scaled Jacobian
    singular_values: np.ndarray
    gram: np.ndarray | None = None  # Js[:, accepted]^T Js[:, accepted] (column-scaled), for the covariance


def priority_order(names: list[str], kinds: list[str]) -> list[int]:
    """Reference points and the instrument frame first (nuisance unknowns absorb what they can), then
    the TCP, joint offsets, base, and link geometry last: when two columns are confounded, the later
    one stays at nominal."""
    return list(_priority_order(tuple(names), tuple(kinds)))


@lru_cache(maxsize=256)
def _priority_order(names: tuple[str, ...], kinds: tuple[str, ...]) -> tuple[int, ...]:

    def rank(i: int) -> tuple[int, int]:
        n, k = names[i], kinds[i]
        if k == "point":
            return 0, i
        if k == "instrument":
            return 1, i
        for p, pre in enumerate(PRIORITY[2:], start=2):
            if n.startswith(pre):
                return p, i
        return len(PRIORITY), i

    return tuple(sorted(range(len(names)), key=rank))


@dataclass
class Decision:
    """What the data identify (before the reasons are worded): accepted columns in acceptance order, the
    remainder norms of weak (noise-rejected) columns, and the length owner dropped for "no known length"."""

    accepted: list[int]
    weak: dict[int, float]
    scale_hit: int | None
    norms: np.ndarray
    tau_struct: float
    margin: float = 1.0  # smallest factor by which a remainder clears the threshold, either way (>= 1)


def decide(Js: np.ndarray, names: list[str], kinds: list[str], *, sigma: float = 0.0, max_std: float = 1e-3,
           scale_dir: np.ndarray | None = None, residual: np.ndarray | None = None) -> Decision:
    """The rank decision of ``analyse`` without the reasons and the singular values (cheap: a few
    Householder QR factorisations); ``analyse(..., decided=...)`` completes it."""
    p = Js.shape[1]
    norms = np.sqrt(np.einsum("ij,ij->j", Js, Js))
    big = norms.max() if p else 0.0
    tau_struct = RTOL * big if big > 0 else np.inf
    tau_noise = sigma / max_std if max_std > 0 else 0.0
    order = priority_order(names, kinds)
    accepted, weak, margin = _greedy(Js, order, tau_struct, tau_noise)
    scale_hit = None
    if _scale_invisible(Js, scale_dir, residual, norms):
        # a uniform scaling of every length only scales the residual: the data have no length standard.
        # The longest link length that would be estimated keeps its nominal value instead (fixing a
        # long one pins the scale best).
        owners = [j for j in accepted if kinds[j] == "model" and scale_dir[j] != 0.0]
        if owners:
            scale_hit = max(owners, key=lambda j: abs(scale_dir[j]))
            accepted, weak, margin = _greedy(Js, [j for j in order if j != scale_hit], tau_struct, tau_noise)
    return Decision(accepted, weak, scale_hit, norms, tau_struct, margin)


def analyse(Js: np.ndarray, names: list[str], kinds: list[str], *, sigma: float = 0.0, max_std: float = 1e-3,
            scale_dir: np.ndarray | None = None, residual: np.ndarray | None = None, n_joints: int = 0,
            first_revolute: bool = True, last_revolute: bool = True,
            decided: Decision | None = None) -> RankAnalysis:
    """``Js`` is the column-scaled Jacobian (m x p); ``scale_dir`` the uniform-scaling direction in the
    same scaled coordinates and ``residual`` the current residual (to detect "no known length").
    ``decided``: the ``decide`` result for these same arguments (not recomputed)."""
    m, p = Js.shape
    d = decided or decide(Js, names, kinds, sigma=sigma, max_std=max_std, scale_dir=scale_dir, residual=residual)
    accepted, weak, norms, tau_struct = d.accepted, d.weak, d.norms, d.tau_struct
    rejected: dict[int, str] = {}
    acc = set(accepted)
    dep = [j for j in range(p) if j not in acc]
    accepted = sorted(accepted)
    A = Js[:, accepted]
    AtA = A.T @ A
    if dep:
        # each dependent column as a combination of the accepted ones (its null-space vector)
        # (normal equations: A has full column rank by construction; the coefficients only rank partners)
        coef = _spd_solve(AtA, A.T @ Js[:, dep]) if accepted else np.zeros((0, len(dep)))
        for c, j in enumerate(dep):
            rejected[j] = _reason(j, coef[:, c], accepted, names, kinds, norms, tau_struct, weak.get(j), sigma,
                                  max_std, j == d.scale_hit, n_joints, first_revolute, last_revolute)
    s = np.sqrt(np.maximum(dsyev(AtA, compute_v=0)[0][::-1], 0.0)) if accepted else np.zeros(0)  # singular values
    r = len(accepted)
    cond = float(s[0] / s[-1]) if r and s[-1] > 0 else None
    o1 = math.exp(float(np.log(s).mean())) / math.sqrt(m) if r and s[-1] > 0 else None
    return RankAnalysis(accepted, rejected, r, cond, o1, s, AtA)


def singular_values(A: np.ndarray) -> np.ndarray:
    """Singular values of a tall full-rank ``A``, descending, from the small Gram matrix (relative accuracy
    ~ eps * cond^2, ample for the condition numbers that pass the rank analysis)."""
    ev = np.linalg.eigvalsh(A.T @ A)[::-1]
    return np.sqrt(np.maximum(ev, 0.0))


def _greedy(Js, order, tau_struct, tau_noise) -> tuple[list[int], dict[int, float], float]:
    """Columns in ``order``; each is accepted when what remains of it after projecting out the columns
    accepted before it exceeds both thresholds. Those remainders are the diagonal of R in a Householder
    QR of the ordered columns, valid up to the first rejected column. Deleting a rejected column from R
    leaves the trailing block ``R[b:, b+1:]`` (the later columns' coordinates orthogonal to everything
    accepted) in Hessenberg form: its own QR gives the next remainders. Only the first factorisation
    depends on the number of samples. Also returns the margin: the smallest factor by which any
    remainder is above (accepted) or below (rejected) the threshold."""
    thr = max(tau_struct, tau_noise)
    accepted: list[int] = []
    weak: dict[int, float] = {}
    margin = np.inf
    cand = list(order)
    if not cand:
        return accepted, weak, margin
    T = _qr_r(Js[:, cand])
    while cand:
        rem = np.abs(np.diagonal(T))
        if len(rem) < len(cand):  # more columns than rows: the rest cannot add rank
            rem = np.concatenate([rem, np.zeros(len(cand) - len(rem))])
        bad = np.flatnonzero(~(rem > thr))
        if not len(bad):
            accepted += cand
            margin = min(margin, float(rem.min()) / thr)
            break
        b = int(bad[0])
        accepted += cand[:b]
        margin = min(margin, float(rem[:b].min()) / thr if b else np.inf, thr / float(rem[b]) if rem[b] else np.inf)
        if rem[b] > tau_struct:
            weak[cand[b]] = float(rem[b])
        cand = cand[b + 1:]
        T = T[b:, b + 1:]
        if cand and T.shape[0]:
            T = _qr_r(T)
    return accepted, weak, margin


def _spd_solve(H: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``H^-1 B`` for a symmetric positive definite ``H`` (Cholesky, LAPACK directly); general solve if not."""
    c, info = dpotrf(H, lower=0, clean=1)
    if info == 0:
        X, info = dpotrs(c, B, lower=0)
        if info == 0:
            return X
    return np.linalg.lstsq(H, B, rcond=None)[0]


_LOWER: dict[tuple[int, int], np.ndarray] = {}


def _qr_r(A: np.ndarray) -> np.ndarray:
    """R of a Householder QR (LAPACK dgeqrf; ``numpy.linalg.qr(A, "r")`` without its Python overhead)."""
    m, n = A.shape
    k = min(m, n)
    R = dgeqrf(A)[0][:k]
    low = _LOWER.get((k, n))
    if low is None:
        low = _LOWER.setdefault((k, n), np.tri(k, n, -1, dtype=bool))
    R[low] = 0.0
    return R


def _scale_invisible(Js, scale_dir, residual, norms=None) -> bool:
    """Scaling every length by (1 + s) changes the residual r into (1 + s) r exactly when no length is
    known, i.e. ``J v = r``: the data carry no length standard (seed 003d's distance argument)."""
    if scale_dir is None or residual is None or not np.any(scale_dir):
        return False
    ref = np.sum((np.linalg.norm(Js, axis=0) if norms is None else norms) * np.abs(scale_dir))
    return bool(np.linalg.norm(Js @ scale_dir - residual) <= 1e-6 * ref)


def _reason(j, a, accepted, names, kinds, norms, tau_struct, weak_norm, sigma, max_std, scale_hit, n_joints,
            first_revolute, last_revolute) -> str:
    name = names[j]
    if scale_hit:
        return ("scale: no known length - every length of the robot and the unknown point(s) can grow "
                "together without changing the data; give a known point or measure with an instrument")
    last = name == f"offset.j{n_joints}" and last_revolute
    if last and norms[j] <= max(tau_struct, sigma / max_std if max_std > 0 else 0.0):
        return f"the TCP lies on the axis of joint {n_joints}: rotating it does not move the tool tip"
    if norms[j] <= tau_struct:
        return "changing it does not move the tool tip in any of these poses"
    contrib = np.abs(a) * norms[accepted]
    order = np.argsort(-contrib)
    cut = 0.2 * contrib.max() if len(contrib) else 0.0
    partners = [names[accepted[k]] for k in order[:4] if contrib[k] > cut]
    if name == "offset.j1" and first_revolute:
        if any(p.startswith("point.") for p in partners):
            return "a rotation about joint 1 moves the unknown point with the robot"
        if any(kinds[names.index(p)] == "instrument" for p in partners):
            return "a rotation about joint 1 is indistinguishable from rotating the unknown instrument frame"
    if last and any(p.startswith("tcp.") for p in partners):
        return (f"the TCP is free: a rotation about joint {n_joints} only turns the TCP offset about that "
                f"axis, which is absorbed by {', '.join(p for p in partners if p.startswith('tcp.'))}")
    with_ = ", ".join(partners) if partners else "the other unknowns"
    if weak_norm is not None:
        std = sigma / weak_norm
        return (f"poorly observed: its standard deviation would be about {std * 1e3:.2g} mm at the tool "
                f"(threshold {max_std * 1e3:.2g} mm); nearly confounded with {with_}")
    return f"confounded with {with_}: the data cannot tell them apart"
