"""Questions asked of the records: each parameter of one unit across its runs (with drift flags), and exports.

Drift: a parameter whose identified value moved between two consecutive runs by more than 3 combined
standard deviations (``|v_i - v_{i-1}| > 3 sqrt(s_i^2 + s_{i-1}^2)``) is flagged; the noise of both runs is
allowed for, so a flag means the unit changed (or a run went wrong), not that the measurement is noisy. Runs
under another kinematic model (``model``) are not compared: the row says ``model_changed`` instead."""

from __future__ import annotations

import math
from datetime import datetime

DRIFT_SIGMA = 3.0


def parameter_trend(sessions: list[dict]) -> dict[str, list[dict]]:
    """``{parameter: [{"session", "started", "value", "std", "unit", "identifiable", "drift_sigma",
    "drift"}...]}`` over full session records (oldest first); SI values. Reference points are left out."""
    out: dict[str, list[dict]] = {}
    for s in sessions:
        params = ((s.get("result") or {}).get("parameters") or {})
        for name, p in params.items():
            if p.get("kind") == "point":
                continue
            row = {"session": s.get("session"), "started": s.get("started"), "value": p.get("value"),
                   "std": p.get("std"), "unit": p.get("unit"), "identifiable": bool(p.get("identifiable")),
                   "drift_sigma": None, "drift": False, "model": s.get("model"), "model_changed": False}
            prev = next((r for r in reversed(out.get(name, [])) if r["identifiable"]), None)
            if prev is not None and row["model"] != prev["model"]:
                # another kinematic model under the same serial: its parameters are not the previous run's, a
                # difference is no drift of the unit (say so instead)
                row["model_changed"] = True
            elif row["identifiable"] and prev is not None and _finite(row["value"], row["std"], prev["value"],
                                                                      prev["std"]):
                comb = math.hypot(row["std"], prev["std"])
                if comb > 0:
                    row["drift_sigma"] = abs(row["value"] - prev["value"]) / comb
                    row["drift"] = row["drift_sigma"] > DRIFT_SIGMA
            out.setdefault(name, []).append(row)
    return out


def _finite(*xs) -> bool:
    return all(x is not None and math.isfinite(float(x)) for x in xs)


def parse_since(text: str | None) -> datetime | None:
    """``--since``: an ISO date or date-time (UTC when no zone is given)."""
    from datetime import UTC

    if not text:
        return None
    try:
        t = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(f"--since {text!r} is not an ISO date or date-time (e.g. 2026-11-01 or "
                         "2026-11-01T08:00:00Z)") from None
    return t if t.tzinfo else t.replace(tzinfo=UTC)


def started_after(summary: dict, since: datetime | None) -> bool:
    if since is None:
        return True
    from datetime import UTC

    try:
        t = datetime.fromisoformat(str(summary.get("started") or "").replace("Z", "+00:00"))
    except ValueError:
        return False
    return (t if t.tzinfo else t.replace(tzinfo=UTC)) >= since


EXPORT_COLUMNS = ("session", "serial", "model", "procedure", "started", "finished", "station", "operator", "status",
                  "verdict", "n_samples", "rms_before_m", "rms_after_m", "parameter", "value", "std", "unit",
                  "identifiable")


def export_rows(records, serial: str | None = None, since: datetime | None = None) -> list[dict]:
    """One row per (session, parameter), SI; a session without a result gives one row without a parameter."""
    rows = []
    for summ in records.sessions(serial):
        if not started_after(summ, since):
            continue
        doc = records.session(summ["session"])
        base = {"session": summ["session"], "serial": summ["serial"], "model": summ.get("model") or doc.get("model"),
                "procedure": summ["procedure"],
                "started": summ["started"], "finished": summ["finished"], "station": summ["station"],
                "operator": summ["operator"], "status": summ["status"],
                "verdict": None if summ["passed"] is None else ("PASS" if summ["passed"] else "FAIL"),
                "n_samples": summ["n_samples"], "rms_before_m": summ["rms_before_m"],
                "rms_after_m": summ["rms_after_m"]}
        params = {k: p for k, p in (((doc.get("result") or {}).get("parameters")) or {}).items()
                  if p.get("kind") != "point"}
        if not params:
            rows.append({**base, "parameter": None, "value": None, "std": None, "unit": None, "identifiable": None})
        for name, p in params.items():
            rows.append({**base, "parameter": name, "value": p.get("value") if p.get("identifiable") else None,
                         "std": p.get("std"), "unit": p.get("unit"), "identifiable": bool(p.get("identifiable"))})
    return rows


def export_sessions(records, serial: str | None = None, since: datetime | None = None) -> list[dict]:
    """Full session summaries with verdict measurements and parameters (JSON export), SI."""
    out = []
    for summ in records.sessions(serial):
        if not started_after(summ, since):
            continue
        doc = records.session(summ["session"])
        out.append({**summ, "verdict": doc.get("verdict"),
                    "parameters": {k: {kk: p.get(kk) for kk in ("value", "std", "nominal", "unit", "identifiable")}
                                   for k, p in (((doc.get("result") or {}).get("parameters")) or {}).items()
                                   if p.get("kind") != "point"}})
    return out
