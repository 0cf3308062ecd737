"""Why a fit did not improve: when the fitted noise is far above what the touch method can produce, or the fit
leaves the residual where it started, the result is not trusted and one line says the likely cause with its
evidence and what to do. Pure: residuals and Jacobians in, a ``dict`` out.

Evidence, from the touches themselves (no model of the cause is assumed by the fit):
* repeatability: touches of one point in (nearly) the same arm configuration see the same kinematic error, so
  their scatter is the touch's own (seating, backlash, reading noise);
* backlash: the residual regressed on each joint's direction of last motion (the sign of its change since the
  previous touch, in recording order) times that joint's effect on the tip: a joint with play reads ``+-b/2``
  depending on the side it came from;
* wrong tip link or tool: the residual regressed on a TCP offset (when the TCP was not identified);
* unseated touches: a heavy tail, many touches far beyond the median residual."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# per-axis noise a working touch method gives (m), and how far above it a fit is "far above"
METHOD_NOISE = {"socket": 0.05e-3, "needle": 0.2e-3, "tracker": 0.03e-3}
FAR = 10.0
STUCK = 0.7  # rms after / before above this (with a residual above 3x the method's noise): nothing improved
SAME_POSE = 0.05  # rad or m: touches this close in every joint are one arm configuration
BACKLASH_R2 = 0.25  # share of the residual the direction-of-motion terms must explain
TIP_R2 = 0.5  # share a TCP offset must explain
HEAVY = 3.0  # a touch beyond this times the median residual is far off
HEAVY_SHARE = 0.1  # share of such touches that says "unseated"
PLAY_SHARE = 0.6  # share of the residual variance in the joints' directions (not at the tip) that says "play"
MAX_PLAY = math.radians(5.0)  # a reading std beyond this is no gear play


def _explained(r: np.ndarray, X: np.ndarray) -> tuple[float, np.ndarray]:
    """Share of ``|r|^2`` that least squares on the columns of ``X`` explains, and the coefficients."""
    keep = np.linalg.norm(X, axis=0) > 0
    b = np.zeros(X.shape[1])
    if not keep.any() or not np.any(r):
        return 0.0, b
    sol, *_ = np.linalg.lstsq(X[:, keep], r, rcond=None)
    b[keep] = sol
    e = r - X @ b
    return float(1.0 - (e @ e) / (r @ r)), b


def _nnls(A: np.ndarray, y: np.ndarray, max_iter: int = 100) -> np.ndarray:
    """``min |A x - y|, x >= 0`` by Lawson and Hanson's active set (a dozen unknowns here; scipy.optimize would cost
    the command ~0.3 s of imports for it)."""
    n = A.shape[1]
    x = np.zeros(n)
    free = np.zeros(n, dtype=bool)
    for _ in range(max_iter):
        w = A.T @ (y - A @ x)
        cand = np.flatnonzero(~free & (w > 1e-12 * max(1.0, float(np.abs(w).max()))))
        if not len(cand):
            break
        free[cand[np.argmax(w[cand])]] = True
        while True:
            z = np.zeros(n)
            z[free] = np.linalg.lstsq(A[:, free], y, rcond=None)[0]
            if np.all(z[free] > 0):
                x = z
                break
            neg = free & (z <= 0)
            alpha = float(np.min(x[neg] / (x[neg] - z[neg])))
            x = x + alpha * (z - x)
            free &= x > 1e-15
            x[~free] = 0.0
    return x


def joint_play(r: np.ndarray, Jq: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Variance components of the residual: ``r_i r_i^T ~ s_t^2 I + sum_j v_j g_ij g_ij^T`` (``g_ij`` joint j's
    effect on touch i's tip) by non-negative least squares on the products' six distinct entries. Returns the
    tip's own std ``s_t`` (seating, the instrument), each joint's reading std ``sqrt(v_j)`` and each joint's
    share of the residual variance. Touch noise sits at the tip, isotropic whatever the pose; play in a joint
    (backlash) moves the tip along that joint's direction of motion, more where its lever is long."""
    n = Jq.shape[2]
    iu = np.triu_indices(3)
    A = np.empty((len(r) * 6, n + 1))
    A[:, 0] = np.tile(np.eye(3)[iu], len(r))
    for j in range(n):
        g = Jq[:, :, j]
        A[:, j + 1] = np.einsum("ni,nj->nij", g, g)[:, iu[0], iu[1]].ravel()
    y = np.einsum("ni,nj->nij", r, r)[:, iu[0], iu[1]].ravel()
    v = _nnls(A, y)
    parts = np.r_[3 * v[0], v[1:] * np.mean(np.sum(Jq**2, axis=1), axis=0)]
    total = float(parts.sum()) or 1.0
    return float(np.sqrt(v[0])), np.sqrt(v[1:]), parts[1:] / total


def nothing_improved(rms_before: float, rms_after: float, sigma: float, method: str) -> bool:
    """The fit is far above what the touch method gives, or left the residual where it started."""
    typical = METHOD_NOISE.get(method, METHOD_NOISE["socket"])
    return sigma > FAR * typical or (rms_after > STUCK * rms_before and sigma > 3.0 * typical)


@dataclass
class _Evidence:
    """What the residual shows, each a candidate cause's share of it (fractions 0..1) or size (m)."""

    rep: float | None  # std per axis between repeat touches of one point in one arm configuration
    pairs: int  # how many such pairs
    r2b: float  # share explained by play along each joint's direction of last motion
    b: np.ndarray  # that play, per joint (half the full width)
    r2t: float  # share explained by a TCP offset alone (0 when the TCP was identified)
    heavy: float  # share of touches far off the median
    tip_sd: float  # the tip's own std per axis (seating, instrument)
    joint_sd: np.ndarray  # each joint's reading std
    share: np.ndarray  # each joint's share of the residual variance

    @property
    def play(self) -> float:
        return float(self.share.sum())

    def repeat_text(self) -> str:
        if self.rep is None:
            return ""
        return f"; repeat touches in one arm configuration scatter {self.rep * 1e3:.2g} mm per axis"


def _repeatability(q: np.ndarray, keys: np.ndarray, r: np.ndarray, act: np.ndarray) -> tuple[float | None, int]:
    """Std per axis between touches of one point in one arm configuration (what no model can fit), and the
    number of pairs it comes from."""
    pairs = []
    for k in dict.fromkeys(keys[act].tolist()):
        idx = act[keys[act] == k]
        for a in range(len(idx)):
            near = idx[a + 1:][np.max(np.abs(q[idx[a + 1:]] - q[idx[a]]), axis=1) < SAME_POSE]
            pairs.extend(np.linalg.norm(r[near] - r[idx[a]], axis=1).tolist())
    rep = float(np.sqrt(np.mean(np.square(pairs)) / 6.0)) if pairs else None  # |d|^2 = 2 x 3 sigma^2
    return rep, len(pairs)


def _gather(q, keys, r, act, Jq, Jtcp) -> _Evidence:
    rep, pairs = _repeatability(q, keys, r, act)
    # backlash: residual against each joint's direction of last motion
    s = np.zeros_like(q)
    s[1:] = np.sign(np.diff(q, axis=0))
    X = (Jq * s[:, None, :])[act].reshape(-1, q.shape[1])
    rr = r[act].ravel()
    r2b, b = _explained(rr, X)
    # wrong tip link / tool
    r2t = 0.0 if Jtcp is None else _explained(rr, Jtcp[act].reshape(-1, 3))[0]
    d = np.linalg.norm(r[act], axis=1)
    heavy = float(np.mean(d > HEAVY * np.median(d))) if np.median(d) > 0 else 0.0
    tip_sd, joint_sd, share = joint_play(r[act], Jq[act])
    return _Evidence(rep, pairs, r2b, b, r2t, heavy, tip_sd, joint_sd, share)


def _joint_amounts(joints, values, joint_names: list[str], revolute: list[bool]) -> str:
    return ", ".join(f"{joint_names[j]} {math.degrees(values[j]):.2g} deg" if revolute[j] else
                     f"{joint_names[j]} {values[j] * 1e3:.2g} mm" for j in joints)


def _backlash_cause(e: _Evidence, joint_names: list[str], revolute: list[bool]) -> tuple[str, str, str]:
    top = [j for j in np.argsort(-np.abs(e.b))[:3] if abs(e.b[j]) > 0]
    parts = _joint_amounts(top, 2 * np.abs(e.b), joint_names, revolute)
    evidence = (f"the residual follows the direction each joint last moved: play of {parts} explains "
                f"{100 * e.r2b:.0f} % of it" + e.repeat_text())
    return "backlash", evidence, ("approach every touch from the same side in each joint (repeat touches "
                                  "approached from one direction), pool more fixture positions in one solve, or "
                                  "model the backlash")


def _play_cause(e: _Evidence, joint_names: list[str], revolute: list[bool]) -> tuple[str, str, str]:
    # joints whose reading std is implausible for play (a joint with almost no lever soaks up anything) are
    # left out of the list, not out of the share
    plausible = [j for j in np.argsort(-e.share) if e.share[j] > 0.05 and (e.joint_sd[j] < MAX_PLAY if revolute[j]
                                                                           else e.joint_sd[j] < 1e-3)]
    top = plausible[:3] or [int(np.argmax(e.share))]
    evidence = (f"the scatter is in the joint readings, not at the tip: reading std "
                f"{_joint_amounts(top, e.joint_sd, joint_names, revolute)} carries {100 * e.play:.0f} % of it, the "
                f"tip's own {e.tip_sd * 1e3:.2g} mm per axis the rest" + e.repeat_text())
    return "backlash (play in the joints)", evidence, (
        "approach every touch from the same side in each joint (repeat touches approached from one direction), "
        "pool more fixture positions in one solve, or model the backlash; until then this scatter is the floor no "
        "calibration gets below")


def _cause(e: _Evidence, sigma: float, has_tcp: bool, joint_names: list[str],
           revolute: list[bool]) -> tuple[str, str, str]:
    """``(cause, evidence, action)``: the first candidate whose share passes its threshold, strongest signs
    first; the model itself when none does."""
    if e.r2t > TIP_R2:
        return ("wrong tip link or tool", f"a TCP offset alone explains {100 * e.r2t:.0f} % of the residual",
                "check --tip-link and --tool (or identify tcp)")
    if e.r2b > BACKLASH_R2:
        return _backlash_cause(e, joint_names, revolute)
    if e.play > PLAY_SHARE:
        return _play_cause(e, joint_names, revolute)
    if e.heavy > HEAVY_SHARE:
        return ("unseated touches", f"{100 * e.heavy:.0f} % of the touches sit more than {HEAVY:g}x the median "
                "residual off", "re-seat those touches (check the ball and the sockets) and record them again")
    if e.rep is not None and e.rep > 0.5 * sigma:
        return ("the touches do not repeat", f"repeat touches in one arm configuration already scatter "
                f"{e.rep * 1e3:.2g} mm per axis ({e.pairs} pairs): backlash or unseated touches",
                "repeat touches approached from one direction, pool more fixture positions in one solve, or model "
                "the backlash")
    evidence = (f"neither the direction of motion ({100 * e.r2b:.0f} %), play in the joints ({100 * e.play:.0f} %)"
                + (f", a TCP offset ({100 * e.r2t:.0f} %)" if has_tcp else "")
                + f" nor far-off touches explain the residual; the tip's own scatter is {e.tip_sd * 1e3:.2g} mm")
    return ("the model does not describe this robot", evidence,
            "check the model (--tip-link, joint order and units of the columns) and identify more (dh)")


def explain(q: np.ndarray, keys: np.ndarray, r: np.ndarray, active: np.ndarray, Jq: np.ndarray,
            Jtcp: np.ndarray | None, rms_before: float, rms_after: float, sigma: float, method: str,
            joint_names: list[str], revolute: list[bool]) -> dict | None:
    """``q`` (N, n) readings in recording order, ``keys`` (N,) the point each touch is on, ``r`` (N, 3) the fitted
    residual (tip - point), ``active`` (N,) touches kept, ``Jq`` (N, 3, n) tip per joint, ``Jtcp`` (N, 3, 3) tip
    per TCP offset (None when the TCP was identified). None when the fit is as good as the method allows."""
    typical = METHOD_NOISE.get(method, METHOD_NOISE["socket"])
    far = sigma > FAR * typical
    stuck = rms_after > STUCK * rms_before and sigma > 3.0 * typical
    if not (far or stuck):
        return None
    act = np.flatnonzero(active)
    if len(act) < 4:
        return None
    head = (f"the fit leaves {sigma * 1e3:.3g} mm per axis, far above what {method} touches give "
            f"(~{typical * 1e3:.2g} mm)" if far else
            f"the fit leaves the residual where it started ({rms_before * 1e3:.3g} -> {rms_after * 1e3:.3g} mm RMS)")
    e = _gather(q, keys, r, act, Jq, Jtcp)
    facts: dict[str, float | str] = {"sigma_m": sigma, "method": method, "method_noise_m": typical}
    if e.rep is not None:
        facts.update(repeatability_m=e.rep, repeat_pairs=e.pairs)
    facts["backlash_explains"] = e.r2b
    if Jtcp is not None:
        facts["tcp_explains"] = e.r2t
    facts["far_touches_share"] = e.heavy
    facts.update(tip_noise_m=e.tip_sd, joint_play_share=e.play, joint_play_std=[float(v) for v in e.joint_sd])
    cause, evidence, action = _cause(e, sigma, Jtcp is not None, joint_names, revolute)
    facts["explained_by"] = cause
    line = f"nothing to trust: {head}; likely cause: {cause} ({evidence}); {action}"
    return {"cause": cause, "evidence": evidence, "action": action, "line": line, "facts": facts}
