"""Posterior uncertainty with priors, and which parameters the data identify.

Notation (docs/solver.md): ``B`` the identification Jacobian (seeds 000/002) of the touch residuals,
``sigma`` the touch noise (m, per axis), ``Lambda = diag(1/sigma_p^2)`` the prior precision of the model
parameters (0 for nuisance unknowns: reference points, the instrument frame). For the estimated set A
and the set K kept at nominal:

    H_A   = B_A^T B_A / sigma^2 + Lambda_A                 (posterior information of A given K)
    G     = -H_A^-1 B_A^T B_K / sigma^2                    (how an error of K moves the estimate of A)
    Cov_A = H_A^-1 + G diag(sigma_p,K^2) G^T               (everything the data leave uncertain)

``Cov_A`` is the "consider" covariance: a parameter kept at nominal contributes its prior variance to
the others'. A model parameter is *identified* (estimated) when the data determine it to within its prior:
with everything not identified at nominal, its posterior std (``H_A^-1``) is at most ``MAX_RATIO`` = 1/sqrt(2)
of its prior std (the data carry at least half its information: their own std is at most the prior's) and,
if asked, within ``max_std`` of tool motion (by Sherman-Morrison, posterior var <= prior var / 2 is exactly
"the data, with the other priors, leave it a std of at most its own prior's"). At that line keeping or dropping
a parameter moves the fit by about its own noise: a touch more or less is no cliff. Weak parameters are
dropped one at a time (the worst first): dropping one changes the others. The reported std is from ``Cov_A``, and
``shrinkage = 1 - std^2 / sigma_p^2`` from it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

MAX_RATIO = math.sqrt(0.5)  # identified: posterior std <= prior std / sqrt(2): the data's own std <= the prior's
NUISANCE_STD = 1e3  # (m or rad) stand-in prior of a nuisance unknown that is kept (structurally free)
COVER = 3.0  # std multiple whose Gaussian coverage (99.73 %) the Student-t correction preserves


def spd_inverse(H: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi)definite matrix, equilibrated (Jacobi) first; pseudo-inverse
    if it is not numerically positive definite."""
    d = np.sqrt(np.diag(H))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    Hn = H * np.outer(d, d)
    try:
        L = np.linalg.cholesky(Hn)
        Li = np.linalg.inv(L)
        inv = Li.T @ Li
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(Hn, rcond=1e-12, hermitian=True)
    return inv * np.outer(d, d)


@dataclass
class Posterior:
    cols: list[int]  # estimated columns A (sorted)
    cov: np.ndarray  # consider covariance over cols (SI), noise part times the Student-t factor squared
    info_inv: np.ndarray  # H_A^-1: the covariance if everything kept were exactly at nominal
    std: np.ndarray  # sqrt(diag(cov))


def posterior(BtB: np.ndarray, cols: list[int], kept: list[int], sigma: float, prior: np.ndarray,
              tfac: float = 1.0, extra: tuple[np.ndarray, np.ndarray] | None = None) -> Posterior:
    """``BtB`` = B^T W B over every unknown (whitened, weighted); ``prior`` the prior std per unknown (inf
    for nuisance). ``kept``: columns held at nominal whose prior variance is propagated. ``extra``:
    further consider errors ``(B^T E, variances)``, E their (whitened) columns - the joints' systematic
    reading errors. ``tfac`` (Student-t) scales the noise part ``H_A^-1`` only: the propagated
    variances do not come from the estimated sigma."""
    cols = sorted(cols)
    lam = np.where(np.isfinite(prior[cols]), 1.0 / np.where(np.isfinite(prior[cols]), prior[cols], 1.0) ** 2, 0.0)
    H = BtB[np.ix_(cols, cols)] / sigma**2 + np.diag(lam)
    Hi = spd_inverse(H)
    cov = Hi * tfac**2
    if kept:
        kp = prior[kept]
        kv = np.where(np.isfinite(kp), kp, NUISANCE_STD) ** 2
        G = -Hi @ BtB[np.ix_(cols, kept)] / sigma**2
        cov = cov + (G * kv) @ G.T
    if extra is not None:
        BtE, ev = extra
        G = -Hi @ BtE[cols] / sigma**2
        cov = cov + (G * ev) @ G.T
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return Posterior(cols, cov, Hi, std)


@dataclass
class Decision:
    accepted: list[int]  # sorted
    post: Posterior
    weak: dict[int, tuple[float, float]]  # dropped column -> (posterior std it would have, prior std)


def decide(BtB: np.ndarray, candidates: list[int], order: list[int], structural_kept: list[int], sigma: float,
           prior: np.ndarray, tool_scale: np.ndarray, max_std: float | None = None, tfac: float = 1.0) -> Decision:
    """Identified set among the structurally identifiable ``candidates``. Each round: the posterior of
    the current set given everything else at nominal (``H_A^-1``); every model parameter must reach
    ``MAX_RATIO`` of its prior (and ``max_std`` at the tool). The worst offender is dropped and the round
    repeated: without it, its partners are better determined. (The prior variance of what is dropped
    is not part of this decision - it would drop the well-determined partners of a weak parameter, which
    then could not carry its error - but it is part of the reported covariance.) ``order``: priority
    order (ties drop the later column)."""
    A = sorted(candidates)
    weak: dict[int, tuple[float, float]] = {}
    rank = {j: i for i, j in enumerate(order)}
    while True:
        post = posterior(BtB, A, [], sigma, prior, tfac)
        worst, score = None, 1.0
        for i, j in enumerate(A):
            if not math.isfinite(prior[j]):
                continue
            s = post.std[i] / (MAX_RATIO * prior[j])
            if max_std is not None:
                s = max(s, post.std[i] * tool_scale[j] / max_std)
            if s > score or (s == score and worst is not None and rank[j] > rank[worst]):
                worst, score = j, s
        if worst is None:
            return Decision(A, post, weak)
        weak[worst] = (float(post.std[A.index(worst)]), float(prior[worst]))
        A.remove(worst)


def t_factor(dof: int) -> float:
    """``t_dof(1 - p/2) / 3`` with ``p = P(|Z| > 3)``: with sigma estimated from ``dof`` degrees of
    freedom, a parameter's error is Student-t distributed; multiplying its std by this factor keeps
    +-3 std at the Gaussian 99.73 % coverage (1.09 at dof 29, 1.01 at dof 300)."""
    if dof <= 0:
        return math.inf
    return _t_quantile(int(dof)) / COVER


_P3 = math.erfc(COVER / math.sqrt(2.0))  # two-sided tail of the normal beyond 3 std


@lru_cache(maxsize=512)
def _t_quantile(nu: int) -> float:
    """``t`` with ``P(|T_nu| > t) = P(|Z| > 3)``: exact series for nu <= 200 (Abramowitz & Stegun 26.7.3/4,
    inverted by bisection), Cornish-Fisher expansion (error < 1e-6 here) beyond."""
    z = COVER
    if nu > 200:
        g1 = (z**3 + z) / 4
        g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96
        g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384
        g4 = (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160
        return z + g1 / nu + g2 / nu**2 + g3 / nu**3 + g4 / nu**4
    lo, hi = z, z
    while _t_tail(hi, nu) > _P3:
        hi *= 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if _t_tail(mid, nu) > _P3:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _t_tail(t: float, nu: int) -> float:
    """``P(|T_nu| > t)`` for integer ``nu`` (A&S 26.7.3 odd, 26.7.4 even)."""
    th = math.atan(t / math.sqrt(nu))
    c2, s = math.cos(th) ** 2, math.sin(th)
    if nu % 2:
        if nu == 1:
            a = 2 * th / math.pi
        else:
            term, tot = 1.0, 1.0
            for k in range(1, (nu - 3) // 2 + 1):
                term *= c2 * (2 * k) / (2 * k + 1)
                tot += term
            a = 2 / math.pi * (th + s * math.cos(th) * tot)
    else:
        term, tot = 1.0, 1.0
        for k in range(1, (nu - 2) // 2 + 1):
            term *= c2 * (2 * k - 1) / (2 * k)
            tot += term
        a = s * tot
    return 1.0 - a
