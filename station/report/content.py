"""``build_report(session) -> dict``: everything the report shows, SI, JSON-ready (this is report.json)."""

from __future__ import annotations

import math
from datetime import datetime

from station import units
from station.records.verdict import finite_or_none, measurement_status, overall_status
from station.report.analysis import coverage, load_session_model, per_pose_residuals, sample_arrays
from station.report.isosection import iso9283_section
from station.report.mapsection import correction_map_section

FORMAT = "station-report/1"


class ReportError(ValueError):
    """The session dict cannot be reported (not a dict, no session id)."""


NO_LIMIT = "NO LIMIT"  # an informational measurement: nothing to judge it against, so neither PASS nor FAIL


def _status(m: dict) -> str:
    """The report's result cell: PASS / MARGINAL / FAIL as judged, or NO LIMIT for a measurement without
    low and high (informational; a "PASS" there would claim a check that never happened)."""
    if finite_or_none(m.get("low")) is None and finite_or_none(m.get("high")) is None:
        return NO_LIMIT
    return measurement_status(m)


def _clean(o):
    """JSON-safe copy: non-finite floats become None (strict JSON has no NaN)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if hasattr(o, "tolist"):
        return _clean(o.tolist())
    return o


def _duration(started, finished) -> float | None:
    try:
        return (datetime.fromisoformat(str(finished)) - datetime.fromisoformat(str(started))).total_seconds()
    except (TypeError, ValueError):
        return None


def param_unit(name: str, p: dict, model=None) -> str:
    """SI unit of a parameter: its ``unit`` when the solver gave one, else the station's one rule
    (``station.units.param_unit``: by name, ``offset.jN`` by the model's joint kind)."""
    if p.get("unit") in ("m", "rad"):
        return p["unit"]
    return units.param_unit(name, model)


def _count(v) -> int:
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else 0


def _note(run: dict) -> str:
    """Why one run of a step did not end done: ``pose 2: DeviceFault: the ball slipped``, the skip reason."""
    info = run.get("info") if isinstance(run.get("info"), dict) else {}
    where = f"pose {info['pose']}: " if isinstance(info.get("pose"), int) else ""
    if run.get("status") == "skipped":
        return f"{where}skipped: {run.get('reason') or ''}".strip()
    if run.get("status") == "failed":
        return f"{where}{run.get('error') or 'failed'}: {run.get('message') or ''}".strip()
    return f"{where}{run.get('status') or ''} (never ended)"


def steps_rows(session: dict) -> list[dict]:
    """The session's steps as the report and ``station records show`` list them (one row per step name, from the
    record's ``steps``): ``name``, ``depth`` (0: a step of the checklist, 1: inside another), ``runs``,
    ``outcome`` (``done``, or the counts that were not), ``status`` (done, skipped, problem), ``duration_s``,
    ``args`` (of a step that ran once) and ``notes`` (why runs did not end done). Entries that are not what the
    engine writes are left out."""
    rows = []
    for e in session.get("steps") or [] if isinstance(session.get("steps"), list) else []:
        if not isinstance(e, dict) or not isinstance(e.get("name"), str):
            continue
        runs = _count(e.get("runs"))
        counts = {k: _count(e.get(k)) for k in ("done", "failed", "skipped", "unfinished")}
        outcome = "done" if counts["done"] == runs else ", ".join(f"{n} {k}" for k, n in counts.items() if n)
        # the report's colour: every run done, only skipped (a choice, e.g. no --apply), or a problem
        status = "done" if outcome == "done" else "skipped" if counts["skipped"] == runs else "problem"
        info = e.get("info") if isinstance(e.get("info"), dict) else {}
        runs_not_done = [r for r in e.get("not_done") or [] if isinstance(r, dict)]
        rows.append({"name": e["name"], "depth": min(_count(e.get("depth")), 4), "runs": runs, "outcome": outcome,
                     "status": status,
                     "duration_s": finite_or_none(e.get("duration_s")),
                     "args": ", ".join(f"{k}={v}" for k, v in info.items()),
                     "notes": [_note(r) for r in runs_not_done]})
    return rows


def build_report(session: dict) -> dict:
    if not isinstance(session, dict) or not session.get("session"):
        raise ReportError("report: the session record must be a dict with a 'session' id")
    result = session.get("result") or None
    verdict = session.get("verdict") or None
    writeback = session.get("writeback") or None
    robot = session.get("robot") or {}
    model, model_note = load_session_model(session)
    arrays = sample_arrays(session)

    header = {
        "session": session.get("session"), "serial": session.get("serial"), "robot": robot,
        "model": session.get("model") or robot.get("model"), "procedure": session.get("procedure"),
        "procedure_sha256": session.get("procedure_sha256"), "operator": session.get("operator"),
        "station": session.get("station"), "started": session.get("started"), "finished": session.get("finished"),
        "duration_s": _duration(session.get("started"), session.get("finished")),
        "n_samples": len(session.get("samples") or []),
        "n_fit": sum(1 for s in arrays["set"] if s == "fit"),
        "n_holdout": sum(1 for s in arrays["set"] if s == "holdout"),
    }
    measurements = [{**m, "status": _status(m)} for m in (verdict or {}).get("measurements") or []]

    parameters, unidentifiable = [], []
    for name, p in ((result or {}).get("parameters") or {}).items():
        unit = param_unit(name, p, model)
        value, nominal = p.get("value"), p.get("nominal")
        corr = None
        if p.get("identifiable") and value is not None and nominal is not None and math.isfinite(float(nominal)):
            corr = float(value) - float(nominal)
        row = {"name": name, "kind": p.get("kind", "model"), "unit": unit, "value": value, "nominal": nominal,
               "correction": corr, "std": p.get("std"), "identifiable": bool(p.get("identifiable")),
               "reason": p.get("reason")}
        parameters.append(row)
        if not row["identifiable"]:
            unidentifiable.append({"name": name, "reason": p.get("reason") or "not identifiable"})

    residuals = dict((result or {}).get("residuals") or {})
    per_pose = per_pose_residuals(session, model, arrays)
    per_pose["seq"] = arrays["seq"] if per_pose["source"].startswith("recomputed") else \
        [s for s, st in zip(arrays["seq"], arrays["set"], strict=True) if st == "fit"][:len(per_pose["before_m"])]
    residual_summary = {k: v for k, v in residuals.items() if not isinstance(v, (list, tuple))}

    wb = None
    if writeback:
        before, after = writeback.get("before") or {}, writeback.get("after") or {}
        rows = []
        for name in dict.fromkeys([*before, *after]):
            b, a = before.get(name), after.get(name)
            known = ((result or {}).get("parameters") or {}).get(name) or {}
            rows.append({"name": name, "unit": param_unit(name, known, model), "before": b, "after": a,
                         "change": None if b is None or a is None else float(a) - float(b)})
        wb = {"applied": bool(writeback.get("applied")), "verified": bool(writeback.get("verified")), "values": rows,
              "phase": writeback.get("phase"), "files": list(writeback.get("files") or [])}

    return _clean({
        "format": FORMAT, "units": "SI (m, rad, s)",
        "header": header,
        "overall": overall_status(verdict),
        "verdict": {"passed": (verdict or {}).get("passed"), "status": (verdict or {}).get("status"),
                    "measurements": measurements} if verdict else None,
        "result": None if result is None else {
            "model": result.get("model"), "converged": result.get("converged"), "iterations": result.get("iterations"),
            "rank": result.get("rank"), "n_parameters": result.get("n_parameters"),
            "condition_number": result.get("condition_number"), "sigma_m": result.get("sigma_m"),
            "settings": result.get("settings") or {}, "notes": result.get("notes") or []},
        "parameters": parameters,
        "unidentifiable": unidentifiable,
        "residuals": {"summary": residual_summary, "holdout": (result or {}).get("holdout"), "per_pose": per_pose},
        "coverage": {**coverage(model, arrays), "model_note": model_note},
        "writeback": wb,
        "steps": steps_rows(session),
        "correction_map": correction_map_section(session),
        "iso9283": iso9283_section(session),
    })
