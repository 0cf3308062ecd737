"""The report's ISO 9283 section: the test cube, then per pose the figures of the nominal model and (with a
calibration) the calibrated one side by side, each with its confidence interval; the distance figures; the
instrument's floor under RP. Everything comes from the session record's ``iso9283`` entry (journaled by the
``iso9283`` procedure, station-iso9283/1 per model), SI."""

from __future__ import annotations

import math

POSE_FIGURES = (("AP_p", "m"), ("RP_l", "m"), ("vAP_p", "m"), ("AP_a", "rad"), ("AP_b", "rad"), ("AP_c", "rad"),
                ("RP_a", "rad"), ("RP_b", "rad"), ("RP_c", "rad"))
DISTANCE_FIGURES = (("AD_p", "m"), ("RD_p", "m"))


def _pair(v) -> list | None:
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        return None
    return [lo, hi] if math.isfinite(lo) else None


def _figure(d: dict, name: str, unit: str) -> dict | None:
    v = d.get(name)
    if not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        return None
    return {"value": float(v), "ci": _pair(d.get(f"{name}_ci")), "unit": unit}


def iso9283_section(session: dict) -> dict | None:
    """``None`` for a session without an ISO test; else ``{judged, models, cycles, confidence, cube, poses:
    [{pose, n, figures: {model: {figure: {value, ci, unit}}}}], distance: {pair, figures: {model: ...}},
    instrument, registration: {model: rms_m}}`` (SI)."""
    iso = session.get("iso9283")
    if not isinstance(iso, dict) or not isinstance(iso.get("results"), dict):
        return None
    results = {m: r for m, r in iso["results"].items() if isinstance(r, dict)}
    models = [m for m in ("nominal", "calibrated") if m in results]
    poses = []
    names = list(dict.fromkeys(p for m in models for p in (results[m].get("poses") or {})))
    for p in names:
        row = {"pose": p, "n": None, "figures": {}}
        for m in models:
            d = (results[m].get("poses") or {}).get(p) or {}
            row["n"] = row["n"] or d.get("n")
            row["figures"][m] = {f: fig for f, u in POSE_FIGURES if (fig := _figure(d, f, u)) is not None}
        poses.append(row)
    distance = None
    for m in models:
        d = results[m].get("distance")
        if isinstance(d, dict):
            distance = distance or {"pair": "-".join(d.get("poses") or []), "D_c": {}, "figures": {}}
            distance["D_c"][m] = d.get("D_c")
            distance["figures"][m] = {f: fig for f, u in DISTANCE_FIGURES if (fig := _figure(d, f, u)) is not None}
    judged = iso.get("judged") if iso.get("judged") in models else models[-1] if models else None
    cube = iso.get("cube") if isinstance(iso.get("cube"), dict) else {}
    registration = {m: (iso.get("registration") or {}).get(m, {}).get("rms_m") for m in models}
    return {"judged": judged, "models": models, "cycles": iso.get("cycles"),
            "confidence": (results.get(judged) or {}).get("confidence"), "cube": cube, "poses": poses,
            "distance": distance, "instrument": (results.get(judged) or {}).get("instrument"),
            "registration": registration, "calibration": iso.get("calibration"), "approach": iso.get("approach")}
