"""The report's correction-map section: which parametric calibration the map was built on (file, sha256,
parameter count, payload) and the held-out rows side by side: nominal, calibrated only, calibrated + map.

Everything comes from the session record: its ``correction_map`` entry (journaled by the ``correction_map``
procedure) and its verdict measurements (``holdout_nominal_rms``, ``holdout_calibrated_*``, ``holdout_*``),
converted back to SI with the unit each was judged in."""

from __future__ import annotations

import math
from pathlib import PurePath

from station import units

# held-out rows: (label, measurement names for RMS, max, rotation RMS); a row without any value is left out
HOLDOUT_ROWS = (
    ("nominal model", "holdout_nominal_rms", None, None),
    ("calibrated only", "holdout_calibrated_rms", "holdout_calibrated_max", "holdout_calibrated_rotation_rms"),
    ("map", "holdout_rms", "holdout_max", "holdout_rotation_rms"),
)


def _si(m: dict | None) -> float | None:
    """A verdict measurement's value in SI (m, rad), or None."""
    if not m or m.get("value") is None:
        return None
    try:
        v = float(m["value"]) * units.factor(str(m.get("unit") or ""), m.get("quantity"))
    except (TypeError, ValueError, units.UnitError):
        return None
    return v if math.isfinite(v) else None


def payload_text(p) -> str | None:
    """``15 kg at [0, 0, 30] mm (tool frame)`` for a journaled payload ``{mass: kg, com: [x, y, z] m}``."""
    try:
        com = ", ".join(f"{float(c) * 1e3:g}" for c in p["com"])
        return f"{float(p['mass']):g} kg at [{com}] mm (tool frame)"
    except (KeyError, TypeError, ValueError):
        return None


def correction_map_section(session: dict) -> dict | None:
    """``None`` for a session without a correction map; else ``{file, mesh, nodes, samples, payload,
    calibration: None | {file, path, sha256, sha256_short, model, parameters, payload}, holdout: [{row, rms_m,
    max_m, rotation_rms_rad, judged}]}`` (SI)."""
    cm = session.get("correction_map")
    if not isinstance(cm, dict):
        return None
    meas = {m.get("name"): m for m in ((session.get("verdict") or {}).get("measurements") or [])
            if isinstance(m, dict)}
    cal = cm.get("calibration") if isinstance(cm.get("calibration"), dict) else None
    the_map = cm.get("map") if isinstance(cm.get("map"), dict) else {}
    mesh = the_map.get("mesh") if isinstance(the_map.get("mesh"), dict) else {}
    shape = [int(n) for n in mesh.get("shape") or [] if isinstance(n, (int, float))]
    samples = ((the_map.get("samples") or {}).get("x") if isinstance(the_map.get("samples"), dict) else None) or []
    calibration = None
    if cal is not None:
        sha = str(cal.get("sha256") or "")
        params = cal.get("parameters") if isinstance(cal.get("parameters"), dict) else {}
        calibration = {"file": PurePath(str(cal.get("path") or "?")).name, "path": cal.get("path"), "sha256": sha,
                       "sha256_short": sha[:12], "model": cal.get("model"), "parameters": len(params),
                       "compliance": sorted(n for n in params if n.startswith("compliance.")),
                       "payload": cal.get("payload")}
    rows = []
    label_map = "calibrated + map" if calibration is not None else "nominal + map"
    for label, rms, mx, rot in HOLDOUT_ROWS:
        if label == "calibrated only" and calibration is None:
            continue
        vals = {"rms_m": _si(meas.get(rms)), "max_m": _si(meas.get(mx)) if mx else None,
                "rotation_rms_rad": _si(meas.get(rot)) if rot else None}
        if all(v is None for v in vals.values()):
            continue
        judged = [n for n in (rms, mx, rot) if n and meas.get(n)
                  and (meas[n].get("low") is not None or meas[n].get("high") is not None)]
        rows.append({"row": label_map if label == "map" else label, **vals, "judged": judged})
    return {"file": cm.get("file"), "mesh": mesh.get("type"), "nodes": math.prod(shape) if shape else None,
            "samples": len(samples), "payload": cm.get("payload"), "payload_text": payload_text(cm.get("payload")),
            "calibration": calibration, "holdout": rows}
