"""Scoring held-out touches with the calibrated model fixed (nothing is re-fitted but reference points).

* A holdout point with a label of the fit (or a known position) is scored against that point: the
  same fixture, other poses.
* A holdout point with a NEW label (the fixture was moved, or another fixture) is re-estimated as the
  mean calibrated tip position of its touches; its *consistency* is the mean distance of each touch from
  that estimate. When the distance between two such points is known (``distances``), the measured one
  is compared with it: a frame-independent check of the length scale.
* With instrument measurements the held-out tip positions are compared with the measurements through
  the fitted instrument frame.

``rms_m`` / ``max_m`` are over every held-out touch: distance from its fit/known point, or from its
re-estimated point for a new label. ``rms_nominal_m``: the same with the nominal model."""

from __future__ import annotations

import math

import numpy as np

from station.solver.observations import Observations, SolverInputError

MOVED_M = 1e-3  # a same-label holdout point this far (plus 10 sigma) from the fit's: the fixture moved


def score(prob, x: np.ndarray, act: list[int], ho: Observations, sigma: float, distances: dict | None) -> dict:
    model = prob.model
    if not isinstance(ho, Observations):
        raise SolverInputError("holdout must be an Observations")
    if ho.q.shape[1] != model.n_joints:
        raise SolverInputError(f"holdout: model {model.name} has {model.n_joints} joints, got {ho.q.shape[1]}")
    xa = prob.x_nominal.copy()
    xa[act] = x[act]
    xn = prob.x_nominal.copy()
    if prob.frame_unknown:  # the instrument frame is always needed to compare, identified or not
        inst = [i for i, k in enumerate(prob.kinds) if k == "instrument"]
        xa[inst] = x[inst]
        xn[inst] = x[inst]
    P = model.position(ho.q, prob.full_params(xa))
    P0 = model.position(ho.q, prob.full_params(xn))
    if prob.instrument:
        if ho.measured is None:
            raise SolverInputError("holdout: the fit used instrument measurements; holdout needs them too")
        rms, mx = _stats(np.linalg.norm(P - ho.measured, axis=1))
        rms0, _ = _stats(np.linalg.norm(P0 - ho.measured, axis=1))
        return {"n_samples": len(ho), "rms_m": rms, "max_m": mx, "rms_nominal_m": rms0}
    if ho.measured is not None:
        raise SolverInputError("holdout: it carries instrument measurements; the fit did not")
    planes = set(prob.obs.point[prob.on_plane].tolist())
    if planes:  # touches of a plane are not on a point: scored only through the plane's fit residual
        keep = np.array([p not in planes for p in ho.point], dtype=bool)
        if not keep.any():
            return {"n_samples": 0, "rms_m": math.nan, "max_m": math.nan, "rms_nominal_m": math.nan,
                    "notes": ["every holdout touch is on a plane: nothing to score"]}
        ho, P, P0 = ho.subset(keep), P[keep], P0[keep]
    fit_pts = prob.points_of(x)
    known = set(prob.known)
    keys = ho.keys
    if len(prob.obs.fixtures) > 1 and ho.fixture is not None:  # the fit's points are LABEL@FIXTURE
        keys = np.array([f"{p}@{f}" for p, f in zip(ho.point, ho.fixture, strict=True)], dtype=object)
    d_ref, d_cons, d_nom = np.zeros(len(ho)), np.zeros(len(ho)), np.zeros(len(ho))
    points, est, notes = {}, {}, []
    for lb in dict.fromkeys(keys.tolist()):
        idx = keys == lb
        c_hat, c0 = P[idx].mean(axis=0), P0[idx].mean(axis=0)
        d_cons[idx] = np.linalg.norm(P[idx] - c_hat, axis=1)
        est[lb] = c_hat
        entry = {"n": int(idx.sum()), "estimate_m": c_hat.tolist(), "consistency_m": float(d_cons[idx].mean())}
        if lb in fit_pts:
            c = np.asarray(fit_pts[lb], dtype=float)
            d_ref[idx] = np.linalg.norm(P[idx] - c, axis=1)
            d_nom[idx] = np.linalg.norm(P0[idx] - c, axis=1)
            moved = float(np.linalg.norm(c_hat - c))
            entry.update(reference="known" if lb in known else "fit", moved_m=moved)
            if moved > MOVED_M + 10 * math.sqrt(3) * sigma:
                notes.append(f"holdout point {lb} is {moved * 1e3:.1f} mm from the fit's {lb}: if the fixture moved, "
                             f"give its touches new labels (a new label is scored by consistency)")
        else:
            d_ref[idx] = d_cons[idx]
            d_nom[idx] = np.linalg.norm(P0[idx] - c0, axis=1)
            entry.update(reference="new", moved_m=None)
        points[lb] = entry
    rms, mx = _stats(d_ref)
    rms0, _ = _stats(d_nom)
    out = {"n_samples": len(ho), "rms_m": rms, "max_m": mx, "rms_nominal_m": rms0,
           "consistency_m": float(d_cons.mean()), "consistency_rms_m": _stats(d_cons)[0], "points": points,
           "distances": _distances(est, distances), "notes": notes}
    return out


def _distances(est: dict[str, np.ndarray], distances: dict | None) -> list[dict]:
    out = []
    for key, d in (distances or {}).items():
        a, b = (str(s) for s in key)
        # the same pair at every fixture position (keys LABEL@FIXTURE)
        for ka in [k for k in est if k == a or k.startswith(a + "@")]:
            kb = b + ka[len(a):]
            if kb in est:
                meas = float(np.linalg.norm(est[ka] - est[kb]))
                out.append({"points": [ka, kb], "known_m": float(d), "measured_m": meas, "error_m": meas - float(d)})
    return out


def _stats(d: np.ndarray) -> tuple[float, float]:
    return float(np.sqrt(np.mean(d**2))), float(d.max())
