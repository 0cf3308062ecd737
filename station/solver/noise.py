"""The touch noise model: isotropic tip noise ``sigma`` (seating, probing) plus a declared random noise of
the joint readings seen through the joint Jacobian (the encoders' quantisation is systematic, not random:
``resolution_of``). Touch i has covariance

    C_i = sigma^2 I + Jq_i diag(sigma_q^2) Jq_i^T

Joint noise is joint-space noise: it lies along the very directions the joint offsets move the tip, so
treating it as isotropic tip noise would misstate the offsets' uncertainty. The estimator works on
whitened residuals ``W_i r_i`` with
``W_i = sqrt(w_i) sigma (C_i)^-1/2``: their covariance is ``sigma^2 I``, so every formula in sigma keeps
its meaning, and without joint noise ``W_i = sqrt(w_i) I``. ``w_i`` are touch weights (0: an excluded
outlier; IRLS weights of a robust loss)."""

from __future__ import annotations

import math

import numpy as np


def joint_noise_of(model, joint_noise) -> np.ndarray:
    """Per-joint std of the random noise of the joint readings (rad or m): ``joint_noise`` (a number or
    one per joint; None: 0)."""
    n = model.n_joints
    if joint_noise is None:
        return np.zeros(n)
    v = np.broadcast_to(np.asarray(joint_noise, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ValueError(f"joint noise must be >= 0 per joint, got {joint_noise!r}")
    return v


def resolution_of(model) -> np.ndarray:
    """Per-joint std of the encoder quantisation, ``tick / sqrt(12)`` (rad or m; 0 without an encoder)."""
    out = np.zeros(model.n_joints)
    for i, j in enumerate(model.joints):
        e = j.encoder
        if e is not None and e.counts_per_unit > 0 and e.gear != 0:
            out[i] = 1.0 / abs(e.counts_per_unit * e.gear) / math.sqrt(12.0)
    return out


def quantisation(q: np.ndarray, resolution: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
    """How the encoders' rounding enters, from the readings themselves. A joint whose readings all lie on
    its encoder grid is quantised; then

    * touches whose reading of the joint is the only one on its tick have an independent rounding error:
      random noise of variance ``tick^2 / 12`` (returned per touch and joint, (N, n));
    * touches sharing a tick share one rounding error, which no number of touches averages away (an
      omx's waist angle is fixed by the point's azimuth: every touch of a point reads the same tick):
      a systematic error, returned as ``(joint, touch mask)`` groups for the consider covariance.

    Readings off the grid (interpolated, filtered or simulated) carry no quantisation term."""
    N, n = q.shape
    var = np.zeros((N, n))
    groups: list[tuple[int, np.ndarray]] = []
    for j in np.flatnonzero(resolution > 0):
        tick = resolution[j] * math.sqrt(12.0)
        k = q[:, j] / tick
        key = np.round(k)
        if np.max(np.abs(k - key)) > 1e-3:
            continue
        _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        var[:, j] = np.where(cnt[inv] == 1, resolution[j] ** 2, 0.0)
        groups += [(int(j), inv == g) for g in np.flatnonzero(cnt > 1)]
    return var, groups


class NoiseModel:
    """Per-touch covariance ``C_i = sigma^2 ((1 - f) I + f Q_i / qbar)`` (``Q_i = Jq_i diag(var_q) Jq_i^T``,
    ``qbar`` its mean eigenvalue) and the whitening ``W_i = sqrt(w_i) sigma C_i^-1/2``, which depends on
    the shape ``f`` only. ``f`` (how much of the touch noise has the joints' shape) and ``sigma`` (the RMS
    noise per axis) are fitted to the residuals by maximum likelihood (``fit_sigma``), or fixed by a
    declared isotropic noise plus the modelled joint noise (``declare``). The mixture is data-driven on
    purpose: rounding erases noise along a joint whose reading sits on one tick (an omx waist), so the
    isotropic part cannot be assumed."""

    def __init__(self, Jq: np.ndarray | None, var_q: np.ndarray, n_touches: int) -> None:
        """``var_q``: variance of each joint reading, (n,) or per touch (N, n)."""
        self.n = n_touches
        self.eig = None
        self.f = 0.0
        if Jq is not None and np.any(var_q > 0):
            v = np.broadcast_to(var_q, (n_touches, Jq.shape[2]))
            Q = np.einsum("nij,nj,nkj->nik", Jq, v, Jq)
            lam, U = np.linalg.eigh(Q)
            lam = np.maximum(lam, 0.0)
            self.qbar = float(lam.mean())
            if self.qbar > 0:
                self.eig = (lam / self.qbar, U)
                self.f = 0.5
        self.w = np.ones(n_touches)
        self._W = None

    @property
    def joint(self) -> bool:
        return self.eig is not None

    def set(self, sigma: float | None = None, w: np.ndarray | None = None) -> None:
        """``sigma`` is accepted for symmetry with the isotropic case; the whitening does not depend on it."""
        if w is not None:
            self.w = w
            self._W = None

    def _shape(self, f: float) -> np.ndarray:
        return (1.0 - f) + f * self.eig[0]  # (N, 3) relative variances along each touch's axes

    def declare(self, sigma_iso: float) -> float:
        """Fix the shape from a declared isotropic noise plus the modelled joint noise; returns sigma."""
        if self.eig is None:
            return sigma_iso
        self.f = self.qbar / (sigma_iso**2 + self.qbar)
        self._W = None
        return math.sqrt(sigma_iso**2 + self.qbar)

    def matrices(self, weighted: bool = True) -> np.ndarray:
        """``W_i`` (N, 3, 3); ``weighted=False``: without the touch weights."""
        if not weighted:
            lam, U = self.eig
            d = 1.0 / np.sqrt(np.maximum(self._shape(self.f), 1e-12))
            return np.einsum("nij,nj,nkj->nik", U, d, U)
        if self._W is None:
            self._W = np.sqrt(self.w)[:, None, None] * self.matrices(False)
        return self._W

    def residual(self, r: np.ndarray, weighted: bool = True) -> np.ndarray:
        if self.eig is None:
            return r * np.repeat(np.sqrt(self.w), 3) if weighted else r
        return np.einsum("nij,nj->ni", self.matrices(weighted), r.reshape(-1, 3)).ravel()

    def jacobian(self, J: np.ndarray, weighted: bool = True) -> np.ndarray:
        if self.eig is None:
            return J * np.repeat(np.sqrt(self.w), 3)[:, None] if weighted else J
        N, p = self.n, J.shape[1]
        return np.einsum("nij,njk->nik", self.matrices(weighted), J.reshape(N, 3, p)).reshape(3 * N, p)

    def fit_sigma(self, r: np.ndarray, dof: int) -> float:
        """sigma (RMS noise per axis) from the residuals with ``dof`` degrees of freedom; with joint noise
        also the shape ``f``, by maximum likelihood over a grid refined by golden section."""
        if dof <= 0:
            return math.inf
        if self.eig is None:
            rw = self.residual(r)
            return math.sqrt(float(rw @ rw) / dof)
        lam, U = self.eig
        y2 = np.einsum("nij,ni->nj", U, r.reshape(-1, 3)) ** 2
        act = self.w > 0
        y2, wt = y2[act], self.w[act][:, None]
        M = 3.0 * float(act.sum())

        def nll(f: float) -> tuple[float, float]:
            v = np.maximum(self._shape(f)[act], 1e-9)
            s2 = float(np.sum(wt * y2 / v)) / M
            return M * math.log(max(s2, 1e-300)) + float(np.sum(wt * np.log(v))), s2

        grid = np.linspace(0.0, 1.0 - 1e-6, 21)
        k = int(np.argmin([nll(f)[0] for f in grid]))
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        g = (math.sqrt(5) - 1) / 2
        for _ in range(30):
            a, b = hi - g * (hi - lo), lo + g * (hi - lo)
            if nll(a)[0] < nll(b)[0]:
                hi = b
            else:
                lo = a
        self.f = 0.5 * (lo + hi)
        self._W = None
        return math.sqrt(nll(self.f)[1] * M / dof)
