"""Which unknowns could these poses identify at all, and why not the others (structure, named by cause).

The question is asked of *perfect* touches: the Jacobian is evaluated at joint readings moved (by a few
micrometres of tip motion) so that every touch lies exactly on its target (``Problem.consistent_q``).
Measured touches break exact dependencies by the noise - "a rotation about joint 1 moves the unknown
point" holds only where the touches agree - and a dependency broken only by noise is not information.

Columns, each normalised to unit length, are visited in priority order (points, instrument frame, TCP,
joint offsets, base, link geometry) by a rank-revealing QR: column j is *structurally dependent* when the
sine of its angle to the span of the columns accepted before it is below ``RTOL`` (1e-6). Dependent
columns keep their nominal value; the cause of each is read from its null-space vector (its combination
of accepted columns) and worded with what would fix it. Whether the *noise* lets the data pin an
accepted column down is the other question: ``station.solver.posterior`` (prior versus posterior)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

RTOL = 1e-6  # sine of the angle between a column and the span of the columns before it: dependent below
PRIORITY = ("point.", "instrument", "tcp.", "offset.", "base.")


@dataclass
class Null:
    """Why a column is structurally unidentifiable, and what would make it identifiable."""

    cause: str  # no_effect | on_axis | point_rotation | instrument_frame | tool_free | tool_vs_point | scale |
    #            rigid_motion | redundant | poses | confounded
    partners: list[str]
    reason: str
    fix: str


@dataclass
class Structure:
    accepted: list[int]  # columns that perfect touches at these poses would identify (acceptance order)
    nulls: dict[int, Null] = field(default_factory=dict)  # column -> cause
    scale_owner: int | None = None  # the length kept at nominal because no length is known


def priority_order(names: list[str], kinds: list[str]) -> list[int]:
    """Reference points and the instrument frame first (nuisance unknowns absorb what they can), then
    the TCP, joint offsets, base, and link geometry last: when two columns are confounded, the later
    one stays at nominal."""
    return list(_priority_order(tuple(names), tuple(kinds)))


@lru_cache(maxsize=256)
def _priority_order(names: tuple[str, ...], kinds: tuple[str, ...]) -> tuple[int, ...]:

    def rank(i: int) -> tuple[int, int]:
        n, k = names[i], kinds[i]
        if k in ("point", "plane"):
            return 0, i
        if k == "instrument":
            return 1, i
        for p, pre in enumerate(PRIORITY[2:], start=2):
            if n.startswith(pre):
                return p, i
        return len(PRIORITY), i

    return tuple(sorted(range(len(names)), key=rank))


def structure(prob, x: np.ndarray, rows: np.ndarray | None = None, keep: Structure | None = None,
              steps: int = 2) -> Structure:
    """The structural analysis of ``prob`` at parameters ``x`` over the touches ``rows`` (bool, per touch).
    ``keep``: a set chosen before (e.g. at the start); it stays the accepted set if it is still
    independent here and nothing else became identifiable (in a redundant group any member can carry
    the group's error, but only the one the fit started with is known to reach this solution).
    ``steps``: Newton steps to consistent touches (one suffices at a fitted solution)."""
    q = prob.consistent_q(x, steps)
    _, J = prob.residual_jacobian(x, q=q)
    if rows is not None and not rows.all():
        J = J[np.repeat(rows, 3)]
        q = q[rows]
    if getattr(prob, "distances", None):
        # a known distance is a row of the problem too (any weight: the question is structural); scaled
        # like the touches of its points so that the column norms stay comparable
        _, G, _ = prob.constraint_rows(x)
        J = np.vstack([J, G * math.sqrt(len(q))])
    return analyse(J, prob, x, q, None if keep is None else keep.accepted, None if keep is None else keep.scale_owner)


def analyse(J: np.ndarray, prob, x: np.ndarray, q: np.ndarray, keep: list[int] | None = None,
            keep_scale: int | None = None) -> Structure:
    names, kinds = prob.names, prob.kinds
    p = J.shape[1]
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))
    big = float(norms.max()) if p else 0.0
    zero = norms <= 1e-12 * big if big > 0 else np.ones(p, bool)
    Jn = J / np.where(zero, 1.0, norms)
    order = [j for j in priority_order(names, kinds) if not zero[j]]
    accepted, _, _ = _greedy(Jn, order, RTOL, 0.0)
    scale_owner = None
    v = _scale_vector(prob, x)
    if v is not None and len(accepted) < len(order):
        ref = float(np.linalg.norm(norms * np.abs(v)))
        if ref > 0 and np.linalg.norm(J @ v) <= 1e-5 * ref:
            # scaling every length (robot and points) leaves perfect touches perfect: no length standard.
            # The longest identified link length keeps its nominal value (it pins the scale best).
            owners = [j for j in accepted if kinds[j] == "model" and v[j] != 0.0]
            if owners:
                scale_owner = max(owners, key=lambda j: abs(v[j]))
                order = [j for j in order if j != scale_owner] + [scale_owner]
                accepted, _, _ = _greedy(Jn, order, RTOL, 0.0)
    if keep is not None and len(keep) == len(accepted) and not any(zero[j] for j in keep):
        kept, _, _ = _greedy(Jn, [j for j in order if j in set(keep)], RTOL, 0.0)
        if len(kept) == len(keep):
            accepted = kept
            if scale_owner is not None:  # the scale stays with the length that carried it before
                scale_owner = keep_scale if keep_scale is not None and keep_scale not in set(keep) else None
    out = Structure(accepted, scale_owner=scale_owner)
    acc = sorted(accepted)
    dep = [j for j in range(p) if j not in set(accepted)]
    if not dep:
        return out
    coef = np.linalg.lstsq(Jn[:, acc], Jn[:, dep], rcond=None)[0] if acc else np.zeros((0, len(dep)))
    for c, j in enumerate(dep):
        out.nulls[j] = _cause(j, coef[:, c], acc, prob, x, q, J, norms, bool(zero[j]), j == scale_owner)
    return out


def _scale_vector(prob, x: np.ndarray) -> np.ndarray | None:
    """d x / d s for scaling every length of the robot and the touched points by (1 + s) about the base
    origin: selected link lengths times their value, points relative to the base position. None when a
    length that is not selected would have to scale too (then the data carry a length standard)."""
    model = prob.model
    if prob.instrument:
        return None
    sel = set(prob.model_names)
    ang = {n for n, u in zip(prob.names, prob.units, strict=True) if u == "rad"}
    from station.solver.problem import angle_params

    angles = angle_params(model)
    for n, val in zip(model.param_names, model.params, strict=True):
        fixed_length = n not in sel and n not in angles and not n.startswith(("offset.", "base."))
        if fixed_length and val != 0.0:
            return None
    if any(model.joints[i].kind != "revolute" for i in range(model.n_joints)):
        return None  # a prismatic reading is a length the scaling cannot change
    # about the world origin when the base position is identified, else about the (fixed) base origin
    free_base = any(f"base.{a}" in sel for a in "xyz")
    tb = np.zeros(3) if free_base else np.array([model.param(f"base.{a}") for a in "xyz"])
    v = np.zeros(len(prob.names))
    for i, n in enumerate(prob.names):
        if prob.kinds[i] == "point":
            v[i] = x[i] - tb["xyz".index(n[-1])]
        elif prob.kinds[i] == "plane":
            if n.endswith(".d"):  # n . p = d about the base origin tb: d - n . tb scales
                k = prob.plane_keys.index(n[len("plane."):-2])
                v[i] = x[i] - float(prob.plane_of(x, k)[0] @ tb)
        elif n not in ang and not n.startswith("offset."):
            v[i] = x[i]  # a link length, a tool length or a base position
    return v if np.any(v) else None


def _cause(j, a, acc, prob, x, q, J, norms, zero, scale) -> Null:
    names, kinds, model = prob.names, prob.kinds, prob.model
    name = names[j]
    nj = model.n_joints
    joint = int(name[8:]) if name.startswith("offset.j") else 0
    revolute = joint > 0 and model.joints[joint - 1].revolute
    if scale:
        return Null("scale", [], "scale: no known length - every length of the robot and the unknown point(s) can "
                    "grow together without changing the data",
                    "give a known point position, a second point at a known distance, or measure with an "
                    "instrument")
    if zero:
        if revolute:
            return Null("on_axis", [], f"the tool tip lies on the axis of joint {joint}: rotating it does not move "
                        "the tip" if joint < nj else f"the TCP lies on the axis of joint {joint}: rotating it does "
                        "not move the tool tip", f"a tool whose tip is off the axis of joint {joint}")
        return Null("no_effect", [], "changing it does not move the tool tip in any of these poses",
                    "poses that move the joints this parameter depends on")
    contrib = np.abs(a)
    ordr = np.argsort(-contrib)
    cut = 0.05 * contrib.max() if len(contrib) else 0.0
    partners = [names[acc[k]] for k in ordr if contrib[k] > cut]
    pk = {kinds[names.index(p)] for p in partners}
    tcp = [p for p in partners if p.startswith("tcp.")]
    if revolute and pk == {"point"}:
        if joint == 1:
            return Null("point_rotation", partners, "a rotation about joint 1 moves the unknown point with the robot",
                        "give the position of a touched point (--reference LABEL=x,y,z)")
        return Null("point_rotation", partners,
                    f"a rotation about joint {joint} moves the unknown point with the robot: joint {joint}'s axis "
                    f"is the same line at every touch of a point (joints 1-{joint - 1} do not change between them)",
                    f"give the position of a touched point, or touch a second point at a known distance with "
                    f"joint{'s 1-' if joint > 2 else ' '}{joint - 1} turned")
    if "instrument" in pk and pk <= {"instrument", "point"}:
        what = "rotating" if revolute else "moving"
        if joint == 1:
            return Null("instrument_frame", partners, "a rotation about joint 1 is indistinguishable from rotating "
                        "the unknown instrument frame", "measure in the robot's base frame (instrument frame known)")
        return Null("instrument_frame", partners, f"indistinguishable from {what} the unknown instrument frame",
                    "measure in the robot's base frame (instrument frame known)")
    if revolute and joint == nj and tcp and pk <= {"model", "point"} and all(
            p.startswith("tcp.") or kinds[names.index(p)] == "point" for p in partners):
        return Null("tool_free", partners,
                    f"the TCP is free: a rotation about joint {joint} only turns the TCP offset about that axis, "
                    f"which is absorbed by {', '.join(tcp)}",
                    "keep the TCP fixed (leave tcp out of the identified set) when it is known")
    if name.startswith("tcp.") and pk == {"point"}:
        return Null("tool_vs_point", partners,
                    f"the tool offset {name} moves every touch of the point the same way (the tool does not tilt "
                    f"enough): it cannot be told from the unknown point's position",
                    "touch with the tool tilted in more directions, or give the point's position")
    if pk == {"point"} and not name.startswith("base."):
        return Null("rigid_motion", partners, "changing it moves every touch of a point the same way: the unknown "
                    "point absorbs it", "give the position of a touched point (--reference LABEL=x,y,z)")
    if name.startswith("base.") and pk <= {"point", "instrument"}:
        return Null("rigid_motion", partners, "a rigid motion of the base moves the tool and the unknown points "
                    "together", "give the positions of at least three touched points (or of one, for a "
                    "translation only)")
    if pk == {"model"}:
        if _model_identity(prob, x, j, a, acc, J, norms):
            return Null("redundant", partners,
                        f"the same effect as {', '.join(partners)} at every possible pose: the data see only their "
                        f"combination, which {'they carry' if len(partners) > 1 else 'it carries'}",
                        "identify only one of them (they are one error in this model)")
        still = _still_joints(q, model)
        joints = f" (joint{'s' if len(still) > 1 else ''} {', '.join(map(str, still))} hardly move here)" if still \
            else ""
        return Null("poses", partners,
                    f"these poses cannot tell it from {', '.join(partners)}{joints}",
                    "poses that move every joint over a wider range, or more points")
    return Null("confounded", partners, f"confounded with {', '.join(partners)}: the data cannot tell them apart",
                "more varied poses, more points or a known point")


def _model_identity(prob, x, j, a, acc, J, norms) -> bool:
    """Is the dependency of model column j on the model columns ``acc`` one of the parameterisation (the
    same at every configuration), or only of these poses? Checked at random configurations."""
    model = prob.model
    rng = np.random.default_rng(0)
    lo, hi = model.lower, model.upper
    qr = rng.uniform(np.maximum(lo, -math.pi), np.minimum(hi, math.pi), (24, model.n_joints))
    _, Jr = prob.folded.evaluate(qr, prob.full_params(x))
    Jr = Jr.reshape(-1, Jr.shape[2])
    # the null vector over the model columns, in parameter units: e_j - sum_k a_k (n_j / n_k) e_k (the
    # caller saw no significant point or instrument coefficient)
    v = np.zeros(prob.n_model)
    v[j] = 1.0
    for k, c in zip(acc, a, strict=True):
        if k < prob.n_model:
            v[k] -= c * norms[j] / norms[k]
    scale = float(np.linalg.norm(Jr * np.abs(v)[None, :], axis=0).sum()) or 1.0
    return bool(np.linalg.norm(Jr @ v) <= 1e-5 * scale)


def _still_joints(q: np.ndarray, model) -> list[int]:
    """Joints whose readings span less than 5 deg (or 5 mm) over the touches."""
    span = q.max(axis=0) - q.min(axis=0)
    return [i + 1 for i in range(model.n_joints) if span[i] < (math.radians(5) if model.joints[i].revolute else 5e-3)]


def _greedy(Js, order, tau_struct, tau_noise) -> tuple[list[int], dict[int, float], float]:
    """Columns in ``order``; each is accepted when what remains of it after projecting out the columns
    accepted before it exceeds both thresholds. Those remainders are the diagonal of R in a Householder
    QR of the ordered columns, valid up to the first rejected column. Deleting a rejected column from R
    leaves the trailing block ``R[b:, b+1:]`` (the later columns' coordinates orthogonal to everything
    accepted) in Hessenberg form: its own QR gives the next remainders. Only the first factorisation
    depends on the number of samples. Also returns the remainders of rejected columns above
    ``tau_struct`` and the margin: the smallest factor by which any remainder is above (accepted) or
    below (rejected) the threshold."""
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


def _qr_r(A: np.ndarray) -> np.ndarray:
    """R of a Householder QR, ``min(m, n)`` rows."""
    return np.linalg.qr(A, mode="r")
