"""A kinematic chain compiled for one identification problem: tool positions and the position Jacobian with
respect to a fixed set of parameters in a few whole-array operations per call.

The chain ``T = E_0 E_1 ... E_{K-1}`` is cut at its joint-driven ("moving") elements into blocks. Inside a
block every element is pose-independent, so:

* runs of elements that are neither moving nor identified are multiplied into constant 4x4 matrices once,
  when the problem is set up (a UR5e chain has 42 elements; a 12-parameter solve keeps ~20 items);
* per call, the block products and the prefixes in front of each identified element are 4x4 products
  (independent of the number of poses);
* the pose-dependent work is one batched product per joint: ``G_{b+1} = G_b (S_b E_b(v))`` with
  ``S_b E(v) = S_b + f1(v) S_b K + f2(v) S_b K^2`` (``K`` the generator of the joint's elementary motion;
  ``f1, f2 = sin v, 1 - cos v`` for a rotation and ``v, 0`` for a translation), all joints at once;
* the Jacobian column of an identified element is the world axis ``w`` of the frame in front of it
  (translation) or ``w x (p_tool - o)`` (rotation), with that frame ``G_b P_k``: one batched product for
  every column together.

Same numbers as ``problem.position_jacobian`` and ``Model.jacobians`` (checked to 1e-12 in
``tests/solver/test_solver_folded.py``)."""

from __future__ import annotations

import numpy as np

from station.kinematics.chain import RX, RY, RZ

_EYE4 = np.eye(4)
_C1, _C2 = np.array([1, 2, 0]), np.array([2, 0, 1])


def _generator_table() -> tuple[np.ndarray, np.ndarray]:
    K = np.zeros((6, 4, 4))
    for ax in range(6):
        if ax < 3:
            K[ax, ax, 3] = 1.0
        else:
            i, j = {RX: (1, 2), RY: (2, 0), RZ: (0, 1)}[ax]
            K[ax, j, i], K[ax, i, j] = 1.0, -1.0
    return K, K @ K


_GEN, _GEN2 = _generator_table()  # E(v) = I + f1(v) K + f2(v) K^2 per axis TX..RZ


def _generators(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``K`` and ``K^2`` (n, 4, 4) for each element axis."""
    axes = np.asarray(axes, dtype=int)
    return _GEN[axes], _GEN2[axes]


def _elementary_batch(axes: np.ndarray, vals: np.ndarray) -> np.ndarray:
    rot = axes >= 3
    f1 = np.where(rot, np.sin(vals), vals)
    f2 = np.where(rot, 1.0 - np.cos(vals), 0.0)
    return _EYE4 + f1[:, None, None] * _GEN[axes] + f2[:, None, None] * _GEN2[axes]


class FoldedChain:
    """``chain`` with every parameter except ``param_idx`` frozen at ``params``.

    ``evaluate(q, params, jacobian=True)`` -> tool positions ``(N, 3)`` and ``d position / d
    params[param_idx]`` as ``(N, 3, k)`` (columns in the order of ``param_idx``); ``params`` must agree
    with the construction values outside ``param_idx`` (they are folded in)."""

    def __init__(self, chain, params: np.ndarray, param_idx) -> None:
        param_idx = np.asarray(param_idx, dtype=int)
        self.n_cols = len(param_idx)
        blocks, want_elem, cols = self._fold(chain, params, {p: c for c, p in enumerate(param_idx.tolist())})
        self._blocks = blocks
        # identified non-moving elements: value = const + param, elementary matrix from the generators
        we = np.array(want_elem, dtype=int)
        self._we_const = chain.const[we]
        self._we_param = chain.param[we]
        self._we_axis = chain.axis[we]
        self._we_translations = bool(np.all(self._we_axis < 3))  # e.g. tcp.x/y/z: E = I + v K
        self._we_K = _GEN[self._we_axis]
        # moving elements in chain order
        mv = np.flatnonzero(chain.joint >= 0)
        self._mv_joint = chain.joint[mv]
        self._mv_const = chain.const[mv]
        self._mv_param = chain.param[mv]
        self._mv_has_p = self._mv_param >= 0
        self._mv_pidx = np.maximum(self._mv_param, 0)
        self._mv_rot = chain.axis[mv] >= 3
        self._mv_axis = chain.axis[mv]
        # the parameter of the first joint-driven element (its offset), -1 if none
        self.first_joint_param = int(chain.param[mv[0]]) if len(mv) else -1
        self._mv_all_rot = bool(np.all(self._mv_rot))
        self._mv_K, self._mv_K2 = _generators(chain.axis[mv])
        self._n_moving = len(mv)
        # Jacobian columns (in chain order) -> output column, rotation mask
        self._cols = np.array(cols, dtype=int)
        self._col_rot = np.array(self._want_axis, dtype=int) >= 3
        self._col_sel = np.array(self._want_axis, dtype=int) % 3
        self._col_block = np.array(self._want_block, dtype=int)
        # columns are in chain order, so each block's columns are a contiguous range
        edges = np.searchsorted(self._col_block, np.arange(self._n_moving + 2))
        self._block_range = [(int(lo), int(hi)) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
        self._rot_cols = np.flatnonzero(self._col_rot)
        self._cols_identity = bool(np.array_equal(self._cols, np.arange(self.n_cols)))
        self._precompute_fixed(len(cols))

    def _fold(self, chain, params: np.ndarray, col_of: dict[int, int]) -> tuple[list[list], list[int], list[int]]:
        """The chain cut into blocks, one per moving element (which closes it) plus the tail; in a block the
        fixed elements between identified ones are multiplied out once. Returns the blocks (items
        ``("const", 4x4)`` or ``("want", identified-element number)``), the chain element of each identified
        non-moving element, and the output column of each Jacobian column (chain order); fills the column
        tables ``_want_block``/``_want_item``/``_want_axis``."""
        moving = (chain.joint >= 0).tolist()
        c_param, c_axis = chain.param.tolist(), chain.axis.tolist()
        blocks: list[list] = [[]]
        want_elem: list[int] = []  # chain element of each identified, non-moving element
        self._want_block: list[int] = []  # block of each Jacobian column's frame
        self._want_item: list[int] = []  # -1: the frame in front of the block's moving element (full product)
        self._want_axis: list[int] = []
        cols: list[int] = []
        pending = None
        # every fixed element's matrix at once (the identified and moving ones are skipped below)
        vals = chain.const + np.where(chain.param >= 0, params[np.maximum(chain.param, 0)], 0.0)
        E_all = _elementary_batch(chain.axis, vals)
        nonzero = (vals != 0.0).tolist()
        for k in range(chain.n_elements):
            pk = c_param[k]
            wanted = pk in col_of
            if (moving[k] or wanted) and pending is not None:
                blocks[-1].append(("const", pending))
                pending = None
            if wanted:
                self._want_block.append(len(blocks) - 1)
                self._want_item.append(-1 if moving[k] else len(want_elem))
                self._want_axis.append(c_axis[k])
                cols.append(col_of[pk])
            if moving[k]:
                blocks.append([])
            elif wanted:
                blocks[-1].append(("want", len(want_elem)))
                want_elem.append(k)
            elif nonzero[k]:
                pending = E_all[k] if pending is None else pending @ E_all[k]
        if pending is not None:
            blocks[-1].append(("const", pending))
        return blocks, want_elem, cols

    def _precompute_fixed(self, nc: int) -> None:
        """What does not depend on the identified values, computed once: products of blocks without
        identified elements, the joint matrices [S, S K, S K^2] behind them, the frames of their columns."""
        blocks = self._blocks
        self._var_blocks = [b for b, items in enumerate(blocks) if any(kind == "want" for kind, _ in items)]
        self._S_fixed = []
        for items in blocks:
            P = _EYE4
            for kind, it in items:
                P = P @ it if kind == "const" else P
            self._S_fixed.append(P)
        nm = self._n_moving
        Sm = np.array(self._S_fixed[:nm]) if nm else np.zeros((0, 4, 4))
        self._XT_fixed = np.concatenate([Sm, Sm @ self._mv_K, Sm @ self._mv_K2], axis=1).transpose(0, 2, 1).copy()
        self._var_moving = [b for b in self._var_blocks if b < nm]
        var = {b for b in self._var_blocks}
        is_var = [it >= 0 or b in var for it, b in zip(self._want_item, self._want_block, strict=True)]
        self._var_cols = np.flatnonzero(np.array(is_var, dtype=bool)) if nc else np.zeros(0, dtype=int)
        self._var_col_src = [(self._want_item[c], self._want_block[c]) for c in self._var_cols]
        # a change of the first joint's value is a rigid motion when nothing identified precedes it
        self.first_joint_shiftable = bool(nm) and not any(b == 0 and it >= 0 for b, it in zip(
            self._want_block, self._want_item, strict=True))
        self._S0_inv = np.linalg.inv(self._S_fixed[0]) if self.first_joint_shiftable else None
        self._VT_fixed = np.zeros((nc, 2, 4))
        for c in range(nc):
            if not is_var[c]:
                F = self._S_fixed[self._want_block[c]]
                self._VT_fixed[c, 0, :3] = F[:3, self._col_sel[c]]
                self._VT_fixed[c, 1] = F[:, 3]

    def first_joint_motion(self, delta: float) -> np.ndarray | None:
        """The rigid motion ``T`` (4x4) that adding ``delta`` to the value of the first joint-driven
        element applies to every tool position, or None when it is not one: ``E(v + d) = E(v) E(d)`` for
        one axis, so with only fixed elements before it (``S_0``), the tool frame becomes
        ``S_0 E(d) S_0^-1`` times the old one. Valid when no identified element precedes that joint."""
        if not self.first_joint_shiftable:
            return None
        E = _elementary_batch(self._mv_axis[:1], np.array([float(delta)]))[0]
        return self._S_fixed[0] @ E @ self._S0_inv

    @property
    def n_items(self) -> int:
        """4x4 factors left per call (constant blocks and identified elements), for tests and the docs."""
        return sum(len(b) for b in self._blocks)

    def evaluate(self, q: np.ndarray, params: np.ndarray, jacobian: bool = True, out: np.ndarray | None = None):
        """Tool positions ``(N, 3)`` and (with ``jacobian``) the Jacobian ``(N, 3, k)``, written into ``out``
        when given (any ``(N, 3, k)`` view, e.g. the model columns of the solver's stacked Jacobian)."""
        if q.ndim != 2:
            q = np.atleast_2d(q)
        N = q.shape[0]
        nm = self._n_moving
        nc = len(self._cols)
        S, prefix = self._block_products(params)
        want_J = jacobian and nc > 0
        if want_J:
            VT = self._column_frames(S, prefix)
            WO = np.empty((2 * nc, 3 * N))
        if nm:
            XT, coef = self._joint_terms(S, params, q)
        # pose-dependent part: the frame at each block start as Gt[c, i, n] = G_n[i, c] (rows 0-2), a (4, 3N)
        # matrix. Joint b: S_b E(v) = sum_t c_t(v) S_b K^t (c = 1, f1, f2), so Gt_{b+1} =
        # [S_b; S_b K; S_b K^2]^T (c (x) Gt_b): one element-wise product and one BLAS product per joint
        Gt = _G0t(N)
        for b in range(nm + 1):
            if want_J:
                lo, hi = self._block_range[b]
                if hi > lo:
                    np.matmul(VT[2 * lo: 2 * hi], Gt.reshape(4, 3 * N), out=WO[2 * lo: 2 * hi])
            if b == nm:
                break
            if b == 0:  # G_0 = I: G_1 = sum_t c_t (S_0 K^t) rows 0-2
                Gt = (XT[0].reshape(4, 3, 4)[:, :, :3].transpose(0, 2, 1).reshape(12, 3) @ coef[0]).reshape(4, 3, N)
            else:
                Gt = (XT[b] @ (coef[b][:, None, None, :] * Gt[None]).reshape(12, 3 * N)).reshape(4, 3, N)
        last = S[nm]
        p = (last[:3, 3] @ Gt[:3].reshape(3, 3 * N)).reshape(3, N) + Gt[3]  # (3, N)
        P = np.ascontiguousarray(p.T)
        if not jacobian:
            return P, None
        J = np.zeros((N, 3, self.n_cols)) if out is None else out
        if not want_J:
            J[...] = 0.0
            return P, J
        self._write_jacobian(J, WO.reshape(nc, 2, 3, N), p)
        return P, J

    def _block_products(self, params: np.ndarray) -> tuple[list, list]:
        """The pose-independent part: each block's product ``S`` (only blocks holding identified elements change
        between calls) and the frame in front of each identified element within its block."""
        S = list(self._S_fixed)
        prefix: list = [None] * len(self._we_param)
        if not self._var_blocks:
            return S, prefix
        if self._we_translations:
            Ew = _EYE4 + (self._we_const + params[self._we_param])[:, None, None] * self._we_K
        else:
            Ew = _elementary_batch(self._we_axis, self._we_const + params[self._we_param])
        for b in self._var_blocks:
            P = None
            for kind, it in self._blocks[b]:
                if kind == "const":
                    P = it if P is None else P @ it
                else:
                    prefix[it] = _EYE4 if P is None else P
                    P = Ew[it] if P is None else P @ Ew[it]
            S[b] = _EYE4 if P is None else P
        return S, prefix

    def _column_frames(self, S: list, prefix: list) -> np.ndarray:
        """The frame in front of each column's element in its block: homogeneous axis direction and origin,
        interleaved rows ``(2 k, 4)``."""
        VT = self._VT_fixed
        if len(self._var_cols):
            VT = VT.copy()
            Fs = np.array([S[b] if it < 0 else prefix[it] for it, b in self._var_col_src])
            vc = self._var_cols
            VT[vc, 0] = Fs[np.arange(len(vc)), :, self._col_sel[vc]]
            VT[vc, 0, 3] = 0.0
            VT[vc, 1] = Fs[:, :, 3]
        return VT.reshape(2 * len(self._cols), 4)

    def _joint_terms(self, S: list, params: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per joint, ``[S_b; S_b K; S_b K^2]^T`` and the coefficients ``(1, f1(v), f2(v))`` of its value at every
        pose ``(nm, 3, N)``: sin and 1 - cos for a rotation, v and 0 for a translation."""
        nm, N = self._n_moving, q.shape[0]
        XT = self._XT_fixed
        if self._var_moving:
            XT = XT.copy()
            vb = self._var_moving
            Sm = np.array([S[b] for b in vb])
            XT[vb] = np.concatenate([Sm, Sm @ self._mv_K[vb], Sm @ self._mv_K2[vb]], axis=1).transpose(0, 2, 1)
        base = self._mv_const + np.where(self._mv_has_p, params[self._mv_pidx], 0.0)
        vm = base[:, None] + q[:, self._mv_joint].T  # (nm, N)
        coef = np.empty((nm, 3, N))
        coef[:, 0] = 1.0
        if self._mv_all_rot:
            np.sin(vm, out=coef[:, 1])
            np.cos(vm, out=coef[:, 2])
            np.subtract(1.0, coef[:, 2], out=coef[:, 2])
        else:
            rot = self._mv_rot[:, None]
            coef[:, 1] = np.where(rot, np.sin(vm), vm)
            coef[:, 2] = np.where(rot, 1.0 - np.cos(vm), 0.0)
        return XT, coef

    def _write_jacobian(self, J: np.ndarray, WO: np.ndarray, p: np.ndarray) -> None:
        """``J`` from each column's world axis and origin ``WO`` (k, 2, 3, N): the axis for a translation,
        axis x (tool - origin) for a rotation."""
        W, O = WO[:, 0], WO[:, 1]  # (nc, 3, N) world axis and origin of each column's element
        rc = self._rot_cols
        if len(rc):
            w, d = W[rc], p[None] - O[rc]  # w x d, component-wise with cyclic index permutations
            W[rc] = w[:, _C1] * d[:, _C2] - w[:, _C2] * d[:, _C1]
        W = W.transpose(2, 1, 0)
        if self._cols_identity:
            J[...] = W
        else:
            J[:, :, self._cols] = W


_G0_CACHE: dict[int, np.ndarray] = {}


def _G0t(N: int) -> np.ndarray:
    """The identity frame for N poses as Gt[c, i, n] = I[i, c] (rows 0-2), (4, 3, N), read-only, cached."""
    G = _G0_CACHE.get(N)
    if G is None:
        if len(_G0_CACHE) > 64:
            _G0_CACHE.clear()
        G = np.ascontiguousarray(np.broadcast_to(_EYE4[:, :3, None], (4, 3, N)))
        G.flags.writeable = False
        _G0_CACHE[N] = G
    return G
