"""``station.records.trend``: a unit's parameters across its runs with drift flags, and the exports, on a real
SQLite records database filled from simulated sessions (``session_factory``)."""

from __future__ import annotations

import math
from datetime import UTC, datetime

import numpy as np
import pytest

from station.records import open_records
from station.records.trend import DRIFT_SIGMA, export_rows, export_sessions, parameter_trend, parse_since


def _session(sid, model, value, std, started="2026-11-21T08:00:00+00:00"):
    return {"session": sid, "started": started, "model": model, "result": {"parameters": {
        "offset.j2": {"value": value, "std": std, "unit": "rad", "identifiable": True, "kind": "model"},
        "point.A.x": {"value": 0.4, "std": 1e-5, "unit": "m", "identifiable": True, "kind": "point"}}}}


def test_drift_is_the_move_over_the_combined_sigma():
    std = 1e-4
    steps = [0.0, 2e-4, 2e-4 + 5 * math.sqrt(2) * std]  # 1.41 sigma (noise), then 5 sigma (a change)
    rows = parameter_trend([_session(f"S{i}", "ur5e", v, std) for i, v in enumerate(steps)])
    assert set(rows) == {"offset.j2"}  # reference points are no parameter of the unit
    r = rows["offset.j2"]
    assert r[0]["drift_sigma"] is None
    assert r[1]["drift_sigma"] == pytest.approx(2e-4 / math.hypot(std, std)) and not r[1]["drift"]
    assert r[2]["drift_sigma"] == pytest.approx(5.0) and r[2]["drift"] and DRIFT_SIGMA < 5.0


def test_another_model_is_not_a_drift():
    rows = parameter_trend([_session("S1", "ur5e", 0.0, 1e-4), _session("S2", "ur5e-cell2", 0.01, 1e-4)])
    assert rows["offset.j2"][1]["model_changed"] and not rows["offset.j2"][1]["drift"]


def test_parse_since():
    assert parse_since("2026-11-01") == datetime(2026, 11, 1, tzinfo=UTC)
    assert parse_since("2026-11-01T08:00:00Z") == datetime(2026, 11, 1, 8, tzinfo=UTC)
    assert parse_since(None) is None
    with pytest.raises(ValueError, match="--since 'last week' is not an ISO date"):
        parse_since("last week")


def test_exports_from_a_database(tmp_path, session_factory):
    url = f"sqlite:///{tmp_path / 'r.db'}"
    stored = [session_factory(seed=s, serial="UR5E-T")[0] for s in (1, 2, 3)]  # started 08:01, 08:02, 08:03
    with open_records(url) as rec:
        for s in stored:
            rec.store_session(s)
        rows = export_rows(rec, "UR5E-T", since=parse_since("2026-11-21T08:02:00Z"))
        sessions = export_sessions(rec, "UR5E-T")
    assert {r["session"] for r in rows} == {stored[1]["session"], stored[2]["session"]}
    for r in rows:
        src = next(s for s in stored if s["session"] == r["session"])["result"]["parameters"][r["parameter"]]
        assert src["kind"] != "point"
        assert r["value"] == (src["value"] if src["identifiable"] else None) and r["unit"] == "rad"
    assert len(sessions) == 3 and all("point.A.x" not in s["parameters"] for s in sessions)
    j3 = [s["parameters"]["offset.j3"]["value"] for s in sessions]
    assert sorted(j3) == sorted(s["result"]["parameters"]["offset.j3"]["value"] for s in stored)
    assert np.isfinite(j3).all()
