"""What the jog UI tells the technician about progress: which reference point to touch next, samples taken /
needed, and whether the samples are "good enough" against the limits that will judge the session.

The good-enough test predicts the posterior standard deviation of every identified parameter from the
Jacobian at the samples recorded so far with an assumed touch noise (not the fitted residual, which is
meaningless with few samples): ``station.solver.predict(..., noise=TOUCH_NOISE)``, the prediction that also checks
a procedure's plan before the robot moves."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from station.engine.limits import NO_LIMITS, Limit

TOUCH_NOISE = 2e-5  # m: assumed repeatability of one touch (one sigma per axis) for the predicted uncertainty


@dataclass
class Check:
    name: str  # the limit's name (samples, identified, fit_rms, offset_std_max, ...)
    text: str  # "12 / 12", "0.004 deg <= 0.01 deg"
    ok: bool | None  # None: not measurable yet


@dataclass
class Guidance:
    taken: int
    needed: int | None  # from the limits' samples.low, else None
    next_point: str | None
    per_point: dict[str, int] = field(default_factory=dict)
    checks: list[Check] = field(default_factory=list)
    status: str = "waiting"  # waiting | not yet | good enough | NO LIMITS
    blocked: dict[str, str] = field(default_factory=dict)  # label -> why the technician is not sent there

    @property
    def good_enough(self) -> bool:
        return self.status == "good enough"


def next_point(labels: list[str], per_point: dict[str, int], blocked: dict[str, str] | None = None) -> str | None:
    """The point with the fewest samples (first in cell order on a tie): spread the touches over every point.
    Never one in ``blocked`` (a socket this arm cannot seat in, a point out of its reach)."""
    labels = [lb for lb in labels if lb not in (blocked or {})]
    if not labels:
        return None
    return min(labels, key=lambda lb: (per_point.get(lb, 0), labels.index(lb)))


def predicted_std(model, q: np.ndarray, labels: np.ndarray, identify: str, reference, noise: float = TOUCH_NOISE
                  ) -> dict[str, float | None]:
    """Predicted posterior std (SI) of every model parameter at these samples with touch noise ``noise``;
    None for a parameter the samples cannot identify (``station.solver.predict``, the same prediction that
    checks a procedure's plan before motion). Raises SolverInputError for too few samples."""
    from station.solver import predict

    pred = predict(model, q, list(labels), identify, reference, noise=noise)
    return {n: (p.std if p.identifiable else None) for n, p in pred.parameters.items()}


FORCED = "forced_samples"  # samples recorded without contact: a jog session with any of them cannot pass


def measurements(model, result, n_samples: int, predicted: dict[str, float | None] | None = None,
                 forced: int = 0) -> dict:
    """The jog session's measurements in SI, by the limit names the procedures use: ``samples``,
    ``identified``, ``fit_rms``, ``fit_max``, ``offset_abs_max``, ``offset_std_max`` (the larger of the fitted
    and the predicted std: an optimistic fit with few samples must not pass), and ``forced_samples``."""
    out: dict[str, tuple[float | None, str]] = {"samples": (float(n_samples), "number"),
                                                FORCED: (float(forced), "number")}
    if result is None:
        return out
    params = result.parameters
    out["identified"] = (float(sum(p.identifiable and p.kind == "model" for p in params.values())), "number")
    out["fit_rms"] = (result.residuals.get("rms_after_m"), "length")
    out["fit_max"] = (result.residuals.get("max_after_m"), "length")
    rev = [(n, p) for n, p in params.items() if n.startswith("offset.") and p.identifiable and p.unit == "rad"]
    if rev:
        out["offset_abs_max"] = (max(abs(p.value - p.nominal) for _, p in rev), "angle")
        stds = [max(p.std or 0.0, (predicted or {}).get(n) or 0.0) for n, p in rev]
        out["offset_std_max"] = (max(stds), "angle")
    return out


def judge(limits: dict[str, Limit], measured: dict, limits_version: str | None) -> dict:
    """A verdict dict as the engine journals it; ``NO LIMITS`` (passed None) when there are no limits."""
    ms = []
    for name, (value, quantity) in measured.items():
        lim = limits.get(name)
        if lim is None and name == FORCED:
            # a forced sample is a pose recorded while the contact input said "no contact", not a touch: the
            # solve built on it is no calibration, whatever the limits file says about the rest
            ms.append({"name": name, "value": value, "unit": "count", "low": None, "high": 0.0, "marginal": False,
                       "passed": not value, "quantity": quantity,
                       "note": "samples recorded without contact (!) are no touches: retake or discard them"})
        elif lim is None:
            ms.append({"name": name, "value": value, "unit": "m" if quantity == "length" else
                       ("rad" if quantity == "angle" else "1"), "low": None, "high": None, "marginal": False,
                       "passed": True, "note": "no limit (informational)", "quantity": quantity})
        else:
            ms.append({**lim.judge(value, quantity), "quantity": quantity})
    for name, lim in limits.items():
        if name not in measured:  # e.g. holdout_rms: a jog session has no holdout; not measured is not a pass
            ms.append({**lim.judge(None, lim.quantity), "quantity": lim.quantity})
    if not limits:
        return {"passed": None, "status": NO_LIMITS, "measurements": ms, "limits_version": limits_version}
    return {"passed": all(m["passed"] for m in ms), "measurements": ms, "limits_version": limits_version}


def guidance(model, labels: list[str], samples: list, result, limits: dict[str, Limit],
             predicted: dict[str, float | None] | None, blocked: dict[str, str] | None = None) -> Guidance:
    per_point = {lb: 0 for lb in labels}
    for s in samples:
        per_point[s.point] = per_point.get(s.point, 0) + 1
    lim_n = limits.get("samples")
    needed = int(np.ceil(lim_n.low)) if lim_n is not None and lim_n.low is not None else None
    blocked = {lb: why for lb, why in (blocked or {}).items() if lb in labels}
    g = Guidance(len(samples), needed, next_point(labels, per_point, blocked), per_point, blocked=blocked)
    if not limits:
        g.status = NO_LIMITS
        return g
    forced = sum(bool((s.status or {}).get("forced")) for s in samples)
    measured = measurements(model, result, len(samples), predicted, forced)
    verdict = judge(limits, measured, None)
    for m in verdict["measurements"]:
        if m.get("low") is None and m.get("high") is None:
            continue  # informational
        if m["name"] == FORCED and not m.get("value"):
            continue  # shown only when there are some
        v = m.get("value")
        bound = " ".join(x for x in (f">= {m['low']:g}" if m.get("low") is not None else "",
                                      f"<= {m['high']:g}" if m.get("high") is not None else "") if x)
        text = f"{'—' if v is None else format(v, '.4g')} {m['unit']} (limit {bound})"
        g.checks.append(Check(m["name"], text, None if v is None else bool(m["passed"])))
    if not samples:
        g.status = "waiting"
    else:
        g.status = "good enough" if all(c.ok for c in g.checks) else "not yet"
    return g
