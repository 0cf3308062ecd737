"""``GET /api/history/{serial}``: the unit's previous runs and each parameter's trend (SI)."""

from __future__ import annotations


def unit_history(serial: str, db: str | None) -> dict:
    from station.records import RecordNotFound, open_records
    from station.records.trend import parameter_trend

    with open_records(db) as rec:
        try:
            rec.robot(serial)
        except RecordNotFound:
            return {"serial": serial, "runs": [], "trend": {}}
        runs = rec.sessions(serial)
        docs = [rec.session(r["session"]) for r in runs]
    out_runs = [{"session": r["session"], "procedure": r["procedure"], "started": r["started"],
                 "operator": r["operator"], "status": r["status"],
                 "verdict": None if r["passed"] is None else ("PASS" if r["passed"] else "FAIL"),
                 "rms_after_m": r["rms_after_m"], "n_samples": r["n_samples"],
                 "report": f"/report/{r['session']}"} for r in runs]
    return {"serial": serial, "runs": out_runs, "trend": parameter_trend(docs)}
