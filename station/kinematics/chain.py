"""A kinematic chain as a sequence of elementary transforms, each owned by one named parameter.

Every model convention (DH, modified DH with Hayati beta, local POE, base and tool frames) compiles
to this form, so forward kinematics and the *analytic* Jacobians with respect to joint values and to
every geometric parameter come from one vectorised routine: the derivative of the tool pose with
respect to the value of element k is the unit twist of that element's axis expressed in the world
frame (``w x (p - o)`` and ``w`` for a rotation, ``w`` and 0 for a translation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TX, TY, TZ, RX, RY, RZ = range(6)
AXIS_NAMES = ("Tx", "Ty", "Tz", "Rx", "Ry", "Rz")


@dataclass(frozen=True)
class Chain:
    """Element k has value ``const[k] + params[param[k]] + q[:, joint[k]]`` (terms absent when -1)."""

    axis: np.ndarray  # (K,) int in TX..RZ
    param: np.ndarray  # (K,) int index into the parameter vector, -1 for none
    joint: np.ndarray  # (K,) int joint index, -1 for a fixed element
    const: np.ndarray  # (K,) float

    @property
    def n_elements(self) -> int:
        return len(self.axis)

    def values(self, q: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Element values ``(N, K)``."""
        N = q.shape[0]
        v = np.broadcast_to(self.const, (N, self.n_elements)).copy()
        has_p = self.param >= 0
        v[:, has_p] += params[self.param[has_p]]
        has_j = self.joint >= 0
        v[:, has_j] += q[:, self.joint[has_j]]
        return v


def _apply(T: np.ndarray, axis: int, v: np.ndarray) -> None:
    """In place ``T <- T @ E(axis, v)`` for a batch ``T (N,4,4)`` and values ``v (N,)``."""
    if axis < 3:
        T[:, :3, 3] += v[:, None] * T[:, :3, axis]
        return
    c, s = np.cos(v)[:, None], np.sin(v)[:, None]
    i, j = {RX: (1, 2), RY: (2, 0), RZ: (0, 1)}[axis]
    ci, cj = T[:, :3, i].copy(), T[:, :3, j]
    T[:, :3, i] = c * ci + s * cj
    T[:, :3, j] = -s * ci + c * cj


def forward(chain: Chain, q: np.ndarray, params: np.ndarray, keep_prefix: bool = False):
    """Tool transform ``(N,4,4)``; with ``keep_prefix`` also the frame before each element ``(N,K,4,4)``."""
    N = q.shape[0]
    v = chain.values(q, params)
    T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
    prefix = np.empty((N, chain.n_elements, 4, 4)) if keep_prefix else None
    for k in range(chain.n_elements):
        if keep_prefix:
            prefix[:, k] = T
        _apply(T, int(chain.axis[k]), v[:, k])
    return (T, prefix) if keep_prefix else T


def element_twists(chain: Chain, T: np.ndarray, prefix: np.ndarray) -> np.ndarray:
    """``(N, 6, K)``: d(tool position, tool orientation)/d(element value), world frame."""
    N, K = prefix.shape[0], chain.n_elements
    p = T[:, :3, 3]
    out = np.zeros((N, 6, K))
    axes = chain.axis
    sel = (axes % 3)[None, :, None, None]
    w = np.take_along_axis(prefix[:, :, :3, :], sel, axis=3)[..., 0]  # (N, K, 3) world axis directions
    rot = axes >= 3
    out[:, :3, ~rot] = np.swapaxes(w[:, ~rot], 1, 2)
    if rot.any():
        o = prefix[:, rot][:, :, :3, 3]
        out[:, :3, rot] = np.swapaxes(np.cross(w[:, rot], p[:, None, :] - o), 1, 2)
        out[:, 3:, rot] = np.swapaxes(w[:, rot], 1, 2)
    return out


@dataclass(frozen=True)
class Fused:
    """A chain for ONE parameter vector: every run of elements without a joint multiplied into one constant
    transform, so a configuration costs one elementary transform per joint element and one product per run
    (a 6-axis DH chain: 42 elements -> 6 + 7). Same tool transform and joint Jacobian as the elements give."""

    between: np.ndarray  # (M+1, 4, 4): before joint element 0, between consecutive ones, after the last
    axis: np.ndarray  # (M,) axis of each joint element
    joint: np.ndarray  # (M,) its joint index
    offset: np.ndarray  # (M,) its value without the joint: const + parameter
    n_joints: int


def fuse(chain: Chain, params: np.ndarray) -> Fused:
    between, axis, joint, offset = [], [], [], []
    T = np.eye(4)[None].copy()
    for k in range(chain.n_elements):
        v = chain.const[k] + (params[chain.param[k]] if chain.param[k] >= 0 else 0.0)
        if chain.joint[k] < 0:
            _apply(T, int(chain.axis[k]), np.array([v]))
            continue
        between.append(T[0])
        T = np.eye(4)[None].copy()
        axis.append(int(chain.axis[k]))
        joint.append(int(chain.joint[k]))
        offset.append(float(v))
    between.append(T[0])
    n = int(chain.joint.max()) + 1 if (chain.joint >= 0).any() else 0
    return Fused(np.array(between), np.array(axis, dtype=int), np.array(joint, dtype=int),
                 np.array(offset, dtype=float), n)


def forward_fused(f: Fused, q: np.ndarray, jacobian: bool = False):
    """Tool transform ``(N,4,4)``; with ``jacobian`` also the joint Jacobian ``(N,6,n)`` (tool position rows,
    then world angular velocity), built from each joint element's world axis as :func:`element_twists` does."""
    N = q.shape[0]
    T = np.broadcast_to(f.between[0], (N, 4, 4)).copy()
    frames = []
    for m in range(len(f.axis)):
        if jacobian:
            frames.append(T[:, :3, :].copy())
        _apply(T, int(f.axis[m]), q[:, f.joint[m]] + f.offset[m])
        T = T @ f.between[m + 1]
    if not jacobian:
        return T
    Jq = np.zeros((N, 6, f.n_joints))
    p = T[:, :3, 3]
    for m, F in enumerate(frames):
        a, j = int(f.axis[m]), int(f.joint[m])
        w = F[:, :, a % 3]
        if a >= 3:
            Jq[:, :3, j] += np.cross(w, p - F[:, :, 3])
            Jq[:, 3:, j] += w
        else:
            Jq[:, :3, j] += w
    return T, Jq


@dataclass(frozen=True)
class Marked:
    """A fused chain that also keeps the frame after chosen elements (link frames for masses, say):
    ``steps`` is the program ``("fixed", M) | ("joint", axis, joint, offset) | ("mark",)`` in chain order."""

    steps: tuple


def fuse_marked(chain: Chain, params: np.ndarray, marks) -> Marked:
    """:func:`fuse` for ONE parameter vector, keeping the frame after each element of ``marks`` (in chain order;
    an element may be marked more than once)."""
    marks = list(marks)
    steps: list[tuple] = []
    T = np.eye(4)[None].copy()
    for k in range(chain.n_elements):
        v = chain.const[k] + (params[chain.param[k]] if chain.param[k] >= 0 else 0.0)
        if chain.joint[k] < 0:
            _apply(T, int(chain.axis[k]), np.array([v]))
        else:
            steps += [("fixed", T[0].copy()), ("joint", int(chain.axis[k]), int(chain.joint[k]), float(v))]
            T = np.eye(4)[None].copy()
        if k in marks:
            steps.append(("fixed", T[0].copy()))
            T = np.eye(4)[None].copy()
            steps += [("mark",)] * marks.count(k)
    steps.append(("fixed", T[0].copy()))
    return Marked(tuple(steps))


def forward_marked(m: Marked, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(tool transform (N,4,4), marked frames (N, marks, 4, 4))`` at joint values ``q (N, n)``."""
    N = q.shape[0]
    T = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
    kept = []
    for step in m.steps:
        if step[0] == "fixed":
            T = T @ step[1]
        elif step[0] == "joint":
            _apply(T, step[1], q[:, step[2]] + step[3])
        else:
            kept.append(T.copy())
    return T, (np.stack(kept, axis=1) if kept else np.zeros((N, 0, 4, 4)))
