"""The live residual plot's data: how far each recorded sample's tool tip is from its reference point.

Before the solve, with the model the session runs on (the nominal model, with the cell's tool): the tip
``model.position(q)`` against the point's surveyed position (``--reference cell``) or, when the point is to be
solved (``--reference unknown``), against the centroid of that point's touches so far (the spread the solve has to
explain). After the solve, the same with the calibrated model (its identified parameters applied) and the solved
point position where the solve estimated one. Distances in mm (what the operator reads), as
``GET /api/state``'s ``residuals`` (docs/panel.md)."""

from __future__ import annotations

import numpy as np


def live_residuals(s) -> tuple[list[dict], str]:
    """``([{"n", "seq", "label", "pose", "set", "mm", "mm_nominal"}, ...], "nominal"|"calibrated")`` for the kept
    samples of the live session ``s`` (a ``station.engine.Session``), in the order they were recorded: ``mm``
    against the current model (calibrated once solved), ``mm_nominal`` against the nominal one."""
    samples = list(s.samples())
    if not samples:
        return [], "nominal"
    q = np.array([smp.q for smp in samples], float)
    labels = [smp.point for smp in samples]
    nominal = _distances(s, s.model, q, labels, {})
    mm, which = nominal, "nominal"
    result = s.result
    if result is not None:
        names = set(s.model.param_names)
        values = {n: p.value for n, p in result.parameters.items()
                  if n in names and p.identifiable and np.isfinite(p.value)}
        solved: dict[str, np.ndarray] = {}
        for n, p in result.parameters.items():  # point.A.x ... of a solved (unknown) reference position
            parts = n.split(".")
            if len(parts) == 3 and parts[0] == "point" and parts[2] in ("x", "y", "z") and p.identifiable:
                solved.setdefault(parts[1], np.full(3, np.nan))["xyz".index(parts[2])] = p.value
        mm, which = _distances(s, s.model.with_params(values), q, labels, solved), "calibrated"
    return ([{"n": i + 1, "seq": smp.seq, "label": smp.point, "pose": smp.pose, "set": smp.set,
              "mm": round(float(a), 6), "mm_nominal": round(float(b), 6)}
             for i, (smp, a, b) in enumerate(zip(samples, mm, nominal, strict=True))], which)


def _distances(s, model, q: np.ndarray, labels: list[str], solved: dict[str, np.ndarray]) -> np.ndarray:
    """mm from each tip to its reference: solved position, else surveyed (``--reference cell``), else the
    centroid of that point's tips."""
    tips = np.atleast_2d(model.position(q))
    surveyed = s.options.get("reference") == "cell" and s.cell is not None
    ref = np.empty_like(tips)
    for label in dict.fromkeys(labels):
        rows = [i for i, lb in enumerate(labels) if lb == label]
        if label in solved and np.all(np.isfinite(solved[label])):
            ref[rows] = solved[label]
        elif surveyed and label in s.cell.points:
            ref[rows] = s.cell.points[label].position
        else:
            ref[rows] = tips[rows].mean(axis=0)
    return np.linalg.norm(tips - ref, axis=1) * 1e3
