"""Numbers the report shows that the session dict does not hold ready-made: per-pose residuals before/after
and the pose coverage (joint range used vs limits, spread of tool orientations).

Computed with the nominal kinematic model named in the session (read-only use of ``station.kinematics``);
when that model cannot be loaded the report says so and shows what the session itself holds."""

from __future__ import annotations

import math

import numpy as np


def load_session_model(session: dict):
    """The nominal model of the session (built-in name or model file path), or (None, why)."""
    from station.kinematics import ModelFileError, load_model

    name = session.get("model") or ((session.get("result") or {}).get("model")) or \
        (session.get("robot") or {}).get("model")
    if not name:
        return None, "the session names no kinematic model"
    try:
        return load_model(str(name)), ""
    except (ModelFileError, KeyError, OSError, ValueError) as e:
        return None, f"model {name!r} could not be loaded ({e})"


def sample_arrays(session: dict) -> dict:
    """q (N,n), labels, sets, measured (N,3)|None, seqs, poses of the session's samples in order."""
    samples = [s for s in session.get("samples") or [] if isinstance(s, dict) and s.get("q") is not None]
    if not samples:
        return {"q": np.zeros((0, 0)), "point": [], "set": [], "measured": None, "seq": [], "pose": []}
    q = np.array([[float(v) for v in s["q"]] for s in samples])
    measured = None
    if all(s.get("measured") is not None for s in samples):
        measured = np.array([[float(v) for v in s["measured"]] for s in samples])
    return {"q": q, "point": [str(s.get("point") or "A") for s in samples],
            "set": [str(s.get("set") or "fit") for s in samples], "measured": measured,
            "seq": [s.get("seq") for s in samples], "pose": [s.get("pose") for s in samples]}


# ---- residuals ---------------------------------------------------------------------------------------
PER_SAMPLE_KEYS = (("per_sample_before_m", "per_sample_after_m"), ("before_m", "after_m"))


def _norms(values) -> np.ndarray | None:
    if values is None:
        return None
    a = np.asarray(values, dtype=float)
    if a.ndim == 2 and a.shape[1] == 3:
        a = np.linalg.norm(a, axis=1)
    return a if a.ndim == 1 else None


def per_pose_residuals(session: dict, model, arrays: dict) -> dict:
    """``{"before_m": [...], "after_m": [...], "set": [...], "source": str}`` per sample (tip error norms, m).

    Recomputed from the samples when the model loads (so held-out poses are included): the tip of the
    nominal model (before) and of the calibrated model (after) against the touched reference point (known;
    or, unknown, the solver's estimate after and, for fit poses, the mean nominal touch before, as the solver
    starts; held-out poses before: vs the estimate, as the solver's ``holdout.rms_nominal_m``) or, with
    an instrument, against the measured point in the instrument frame the solver found. Otherwise taken from
    per-sample arrays in the result (``residuals.per_sample_before_m`` / ``per_sample_after_m``, fit samples
    in order) when the solver provides them."""
    result = session.get("result") or {}
    empty = {"before_m": [], "after_m": [], "set": [], "source": ""}
    if not result.get("parameters"):
        return {**empty, "source": "no solver result in this session"}
    # recomputed when possible: it covers held-out poses too, which the solver never saw
    if model is not None and arrays["q"].size and arrays["q"].shape[1] == model.n_joints:
        out = _recompute(result, model, arrays)
        if out is not None:
            return out
    res = result.get("residuals") or {}
    fit_sets = [s for s in arrays["set"] if s == "fit"]
    for kb, ka in PER_SAMPLE_KEYS:
        b, a = _norms(res.get(kb)), _norms(res.get(ka))
        if b is not None and a is not None and len(b) == len(a):
            sets = fit_sets if len(fit_sets) == len(b) else ["fit"] * len(b)
            return {"before_m": b.tolist(), "after_m": a.tolist(), "set": sets, "source": "solver"}
    return {**empty, "source": "per-pose residuals need the samples and the kinematic model, or per-sample "
            "arrays in the result"}


def _recompute(result: dict, model, arrays: dict) -> dict | None:
    q = arrays["q"]
    params = result["parameters"]
    known = set(model.param_names)
    model_vals = {n: float(p["value"]) for n, p in params.items()
                  if p.get("identifiable") and p.get("kind", "model") == "model" and n in known}
    inst_vals = {n: float(p["value"]) for n, p in params.items()
                 if p.get("kind") == "instrument" and n in known and _finite(p.get("value"))}
    calibrated = model.with_params({**model_vals, **inst_vals})
    before_model = model.with_params(inst_vals)
    p_before, p_after = before_model.position(q), calibrated.position(q)
    if arrays["measured"] is not None:
        target_b = target_a = arrays["measured"]
        source = "recomputed: tip vs instrument measurement (before: nominal model in the solved instrument frame)"
    else:
        ref = (result.get("settings") or {}).get("reference")
        given = ref if isinstance(ref, dict) else {}
        solved: dict[str, list[float]] = {}
        for n, p in params.items():
            if p.get("kind") == "point" and n.count(".") == 2:
                _, label, axis = n.split(".")
                if axis in "xyz":  # a coordinate the data could not identify has no value: NaN
                    solved.setdefault(label, [math.nan] * 3)["xyz".index(axis)] = (
                        float(p["value"]) if _finite(p.get("value")) else math.nan)
        labels = arrays["point"]
        target_a = np.zeros_like(p_after)
        target_b = np.zeros_like(p_before)
        fit = np.array([s == "fit" for s in arrays["set"]])
        for label in set(labels):
            m = np.array([lb == label for lb in labels])
            if label in given:
                pt_a = pt_b = np.asarray(given[label], dtype=float)
            elif label in solved and np.all(np.isfinite(solved[label])):
                pt_a = np.array(solved[label])
                # before: where the uncalibrated robot thinks it touched (mean of its fit touches)
                sel = m & fit if (m & fit).any() else m
                pt_b = p_before[sel].mean(axis=0)
            else:
                return None  # the point is neither given nor solved: nothing to compare with
            target_a[m], target_b[m] = pt_a, pt_b
            # held-out poses did not shape the estimate: before = nominal model vs the estimated point
            target_b[m & ~fit] = pt_a
        source = ("recomputed: tip vs reference point (before: nominal model vs the mean of its fit touches, "
                  "held-out poses vs the estimated point)")
    return {"before_m": np.linalg.norm(p_before - target_b, axis=1).tolist(),
            "after_m": np.linalg.norm(p_after - target_a, axis=1).tolist(),
            "set": list(arrays["set"]), "source": source}


def _finite(v) -> bool:
    try:
        return math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


# ---- coverage ----------------------------------------------------------------------------------------
def coverage(model, arrays: dict) -> dict:
    """Joint range used per joint (and as a fraction of its limits) and the tool-axis orientation spread."""
    q = arrays["q"]
    if q.size == 0:
        return {"joints": [], "tool": None, "note": "no samples"}
    joints = []
    for i in range(q.shape[1]):
        lo = hi = None
        name, kind = f"j{i + 1}", "revolute"
        if model is not None and i < model.n_joints:
            j = model.joints[i]
            lo, hi, name, kind = float(j.lower), float(j.upper), j.name or name, j.kind
        used = float(q[:, i].max() - q[:, i].min())
        span = None if lo is None else hi - lo
        joints.append({"joint": name, "kind": kind, "min": float(q[:, i].min()), "max": float(q[:, i].max()),
                       "used": used, "lower": lo, "upper": hi,
                       "fraction": None if not span else used / span})
    tool = None
    note = ""
    if model is not None and q.shape[1] == model.n_joints:
        T = model.fk(q)
        if T.ndim == 2:
            T = T[None]
        z = T[:, :3, 2]
        mean = z.mean(axis=0)
        mean /= np.linalg.norm(mean)
        cone = np.degrees(np.arccos(np.clip(z @ mean, -1, 1)))
        pair = np.degrees(np.arccos(np.clip(_min_pairwise_dot(z), -1, 1)))
        tool = {"axis": z.tolist(), "mean_axis": mean.tolist(), "cone_deg": cone.tolist(),
                "max_from_mean_deg": float(cone.max()), "max_pairwise_deg": float(pair.max()),
                "tilt_deg": np.degrees(np.arccos(np.clip(-z[:, 2], -1, 1))).tolist(),
                "azimuth_deg": np.degrees(np.arctan2(z[:, 1], z[:, 0])).tolist()}
    else:
        note = "tool orientation needs the kinematic model"
    return {"joints": joints, "tool": tool, "note": note}


def _min_pairwise_dot(z: np.ndarray, exact_up_to: int = 2000, candidates: int = 500, chunk: int = 256) -> float:
    """Smallest dot product between two of the unit vectors ``z`` (the widest pair of tool axes) in memory linear
    in N (100k samples must not build an N x N matrix). Up to ``exact_up_to`` vectors every pair is
    compared (in row chunks); beyond, the ``candidates`` vectors farthest from the mean axis are compared with
    all — the widest pair of a cone of axes has an end on its rim."""
    n = len(z)
    rows = np.arange(n)
    if n > exact_up_to:
        mean = z.mean(axis=0)
        rows = np.argsort(z @ mean)[:candidates]
    best = 1.0
    for s in range(0, len(rows), chunk):
        best = min(best, float((z[rows[s:s + chunk]] @ z.T).min()))
    return best
