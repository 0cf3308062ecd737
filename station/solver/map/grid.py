"""A rectilinear grid over configuration space and the two interpolations of the correction map (docs/map.md) on it.

``multilinear`` interpolates inside each grid cell from its 2^n corners; ``barycentric`` splits every cell
into the n! simplices of its Kuhn (Freudenthal) triangulation and interpolates linearly in the simplex that
holds the point. Both extrapolate beyond the sampled box from the outermost cell (the local coordinates
simply leave [0, 1]): multilinear fields (grid) and affine fields (both) are reproduced exactly everywhere.
``fill`` gives grid nodes without a measurement (configurations the robot cannot assemble) the values of the
smoothest field through the measured ones: least squares on the second differences, so an affine field is
continued exactly. Everything is vectorised over query points; values may be vectors (a column per actuator)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

MESHES = ("grid", "simplex")


@dataclass(frozen=True)
class Grid:
    levels: tuple[np.ndarray, ...]  # per axis, strictly increasing (one level: the axis is constant)

    def __post_init__(self) -> None:
        for i, lv in enumerate(self.levels):
            if lv.ndim != 1 or lv.size < 1 or np.any(np.diff(lv) <= 0):
                raise ValueError(f"grid axis {i + 1}: levels must be strictly increasing, got {lv.tolist()}")

    @classmethod
    def of(cls, levels) -> Grid:
        return cls(tuple(np.asarray(lv, dtype=float).reshape(-1) for lv in levels))

    @property
    def n(self) -> int:
        return len(self.levels)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(lv.size for lv in self.levels)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def strides(self) -> np.ndarray:
        """Flat index = sum(index * strides) (C order: the last axis varies fastest)."""
        s = np.ones(self.n, dtype=np.int64)
        for i in range(self.n - 2, -1, -1):
            s[i] = s[i + 1] * self.shape[i + 1]
        return s

    @property
    def lower(self) -> np.ndarray:
        return np.array([lv[0] for lv in self.levels])

    @property
    def upper(self) -> np.ndarray:
        return np.array([lv[-1] for lv in self.levels])

    def nodes(self) -> np.ndarray:
        """All node coordinates ``(M, n)`` in flat-index order."""
        mesh = np.meshgrid(*self.levels, indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=1)

    def index_of(self, idx: np.ndarray) -> np.ndarray:
        return np.asarray(idx, dtype=np.int64) @ self.strides

    # ---- locating points --------------------------------------------------------------------
    def locate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell base index ``(N, n)`` and local coordinates ``t (N, n)`` (outside [0, 1] beyond the grid).
        An axis with one level has cell 0 and t = 0 (the field is constant along it)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        N = x.shape[0]
        base = np.zeros((N, self.n), dtype=np.int64)
        t = np.zeros((N, self.n))
        for i, lv in enumerate(self.levels):
            if lv.size == 1:
                continue
            k = np.clip(np.searchsorted(lv, x[:, i], side="right") - 1, 0, lv.size - 2)
            base[:, i] = k
            t[:, i] = (x[:, i] - lv[k]) / (lv[k + 1] - lv[k])
        return base, t

    def _steps(self) -> np.ndarray:
        """Flat-index step along each axis, 0 for a one-level axis (its 'upper' corner is the same node)."""
        return np.where(np.array(self.shape) > 1, self.strides, 0)

    def nearest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat index of the nearest node ``(N,)`` and, per axis, the distance to it in units of the local
        level spacing ``(N, n)`` (0 means exactly on the node)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        idx = np.zeros(x.shape, dtype=np.int64)
        rel = np.zeros(x.shape)
        for i, lv in enumerate(self.levels):
            k = np.clip(np.searchsorted(lv, x[:, i]), 0, lv.size - 1)
            km = np.clip(k - 1, 0, lv.size - 1)
            k = np.where(np.abs(x[:, i] - lv[km]) <= np.abs(x[:, i] - lv[k]), km, k)
            idx[:, i] = k
            spacing = np.min(np.diff(lv)) if lv.size > 1 else max(abs(lv[0]), 1.0)
            rel[:, i] = np.abs(x[:, i] - lv[k]) / spacing
        return self.index_of(idx), rel

    # ---- interpolation ----------------------------------------------------------------------
    def multilinear(self, values: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``values (M, k)`` at the nodes -> ``(N, k)`` at ``x (N, n)``."""
        return _chunked(self._multilinear, values, x)

    def _multilinear(self, values: np.ndarray, x: np.ndarray) -> np.ndarray:
        base, t = self.locate(x)
        N = t.shape[0]
        # corner weights built one axis at a time (corner c: bit i of its index <-> upper node along axis i)
        w = np.ones((N, 1))
        idx = (base @ self.strides)[:, None]
        for i, step in enumerate(self._steps()):
            ti = t[:, i:i + 1]
            w = np.concatenate([w * (1.0 - ti), w * ti], axis=1)
            idx = np.concatenate([idx, idx + step], axis=1)
        return (w[:, None, :] @ values[idx])[:, 0]

    def barycentric(self, values: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Linear interpolation in the Kuhn simplex holding each point: sort the local coordinates
        descending, t_(1) >= ... >= t_(n); the simplex's vertices walk from the cell's base corner one
        axis at a time in that order, with weights 1 - t_(1), t_(1) - t_(2), ..., t_(n)."""
        return _chunked(self._barycentric, values, x)

    def _barycentric(self, values: np.ndarray, x: np.ndarray) -> np.ndarray:
        base, t = self.locate(x)
        N = t.shape[0]
        order = np.argsort(-t, axis=1, kind="stable")
        ts = np.take_along_axis(t, order, axis=1)
        w = np.empty((N, self.n + 1))
        w[:, 0] = 1.0 - ts[:, 0]
        w[:, 1:-1] = ts[:, :-1] - ts[:, 1:]
        w[:, -1] = ts[:, -1]
        steps = self._steps()[order]  # (N, n)
        idx = np.empty((N, self.n + 1), dtype=np.int64)
        idx[:, 0] = base @ self.strides
        idx[:, 1:] = idx[:, :1] + np.cumsum(steps, axis=1)
        return (w[:, None, :] @ values[idx])[:, 0]

    def interpolate(self, values: np.ndarray, x: np.ndarray, mesh: str) -> np.ndarray:
        if mesh == "grid":
            return self.multilinear(values, x)
        if mesh == "simplex":
            return self.barycentric(values, x)
        raise ValueError(f"mesh must be one of {', '.join(MESHES)}, got {mesh!r}")

    def simplices(self) -> np.ndarray:
        """Every Kuhn simplex of the grid as ``n + 1`` node indices ``(S, n + 1)`` (for export/inspection)."""
        cells = np.stack([m.reshape(-1) for m in np.meshgrid(*[np.arange(max(s - 1, 1)) for s in self.shape],
                                                             indexing="ij")], axis=1)
        perms = np.array(list(itertools.permutations(range(self.n))), dtype=np.int64)
        steps = self._steps()[perms]  # (P, n)
        walk = np.concatenate([np.zeros((len(perms), 1), dtype=np.int64), np.cumsum(steps, axis=1)], axis=1)
        return ((cells @ self.strides)[:, None, None] + walk[None]).reshape(-1, self.n + 1)

    # ---- filling nodes without a measurement ---------------------------------------------------
    def fill(self, values: np.ndarray, known: np.ndarray) -> np.ndarray:
        """``values (M, k)`` with the rows where ``known`` is False replaced by the smoothest continuation:
        minimise the squared second differences along every axis and the mixed differences of every cell
        face (index space, spacing-weighted), with a vanishing pull towards the affine least-squares fit of
        the known values so the answer is unique. Affine fields are continued exactly."""
        values = np.asarray(values, dtype=float).copy()
        known = np.asarray(known, dtype=bool)
        miss = np.flatnonzero(~known)
        if miss.size == 0:
            return values
        if not known.any():
            raise ValueError("no measured node to continue from")
        D = self._curvature_operator()
        col = np.full(self.size, -1, dtype=np.int64)
        col[miss] = np.arange(miss.size)
        Du = D[:, miss]
        Dk = D[:, np.flatnonzero(known)]
        nodes = self.nodes()
        prior = _affine_fit(nodes[known], values[known], nodes[miss])
        A = (Du.T @ Du).tocsc()
        scale = max(float(A.diagonal().mean()) if A.nnz else 0.0, 1.0)
        delta = 1e-9 * scale
        A = A + delta * sp.identity(miss.size, format="csc")
        rhs = -(Du.T @ (Dk @ values[known])) + delta * prior
        solve = spla.factorized(A)
        values[miss] = np.column_stack([solve(np.ascontiguousarray(rhs[:, j])) for j in range(values.shape[1])])
        return values

    def _curvature_operator(self) -> sp.csr_matrix:
        rows, cols, vals = [], [], []
        r = 0
        grid_idx = np.stack([m.reshape(-1) for m in np.meshgrid(*[np.arange(s) for s in self.shape],
                                                                indexing="ij")], axis=1)
        flat = np.arange(self.size)
        for i, lv in enumerate(self.levels):
            if lv.size < 3:
                continue
            sel = flat[(grid_idx[:, i] > 0) & (grid_idx[:, i] < lv.size - 1)]
            k = grid_idx[sel, i]
            h1, h2 = lv[k] - lv[k - 1], lv[k + 1] - lv[k]
            s = (h1 + h2) ** 2 / 4  # uniform spacing gives 1, -2, 1
            wm, w0, wp = 2 * s / (h1 * (h1 + h2)), -2 * s / (h1 * h2), 2 * s / (h2 * (h1 + h2))
            st = self.strides[i]
            n_ = sel.size
            rr = r + np.arange(n_)
            rows += [rr, rr, rr]
            cols += [sel - st, sel, sel + st]
            vals += [wm, w0, wp]
            r += n_
        for i, j in itertools.combinations(range(self.n), 2):
            if self.shape[i] < 2 or self.shape[j] < 2:
                continue
            sel = flat[(grid_idx[:, i] < self.shape[i] - 1) & (grid_idx[:, j] < self.shape[j] - 1)]
            si, sj = self.strides[i], self.strides[j]
            n_ = sel.size
            rr = r + np.arange(n_)
            rows += [rr] * 4
            cols += [sel, sel + si, sel + sj, sel + si + sj]
            vals += [np.ones(n_), -np.ones(n_), -np.ones(n_), np.ones(n_)]
            r += n_
        if r == 0:
            return sp.csr_matrix((0, self.size))
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(r, self.size))


CHUNK = 4096  # query points per pass: the gathered corner values stay in cache


def _chunked(fn, values: np.ndarray, x: np.ndarray) -> np.ndarray:
    x = np.atleast_2d(np.asarray(x, dtype=float))
    if len(x) <= CHUNK:
        return fn(values, x)
    return np.concatenate([fn(values, x[i:i + CHUNK]) for i in range(0, len(x), CHUNK)])


def _affine_fit(x: np.ndarray, v: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Affine least-squares fit of ``v`` over ``x`` evaluated ``at`` (the mean when too few points)."""
    lo, span = x.min(axis=0), np.maximum(np.ptp(x, axis=0), 1e-12)
    X = np.column_stack([np.ones(len(x)), (x - lo) / span])
    A = np.column_stack([np.ones(len(at)), (at - lo) / span])
    if len(x) < X.shape[1]:
        return np.broadcast_to(v.mean(axis=0), (len(at), v.shape[1])).copy()
    coef = np.linalg.lstsq(X, v, rcond=None)[0]
    return A @ coef


def grid_levels(lower: np.ndarray, upper: np.ndarray, q, exclude_ends: bool = False) -> list[np.ndarray]:
    """Seed [0032]: each actuator interval [a(i), b(i)] split into Q(i) equal sub-intervals; the Q(i) + 1
    boundaries W(0, i) = a(i) < ... < W(Q(i), i) = b(i) are the levels. ``exclude_ends`` drops W(0, i) and
    W(Q(i), i), so the sampled box lies strictly inside the actuator box and the map extrapolates to its
    faces. ``q``: one Q for every axis or one per axis."""
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    qs = np.broadcast_to(np.asarray(q, dtype=int), lower.shape)
    out = []
    for i, (lo, hi, Q) in enumerate(zip(lower, upper, qs, strict=True)):
        if Q < 1:
            raise ValueError(f"axis {i + 1}: Q must be at least 1, got {Q}")
        if exclude_ends and Q < 2:
            raise ValueError(f"axis {i + 1}: without the interval ends Q must be at least 2 (Q - 1 levels), got {Q}")
        lv = np.linspace(lo, hi, int(Q) + 1)
        out.append(lv[1:-1] if exclude_ends else lv)
    return out
