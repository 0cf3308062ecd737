"""``station.panel.history``: ``GET /api/history/{serial}``: a unit's runs and parameter trend from a real
records database."""

from __future__ import annotations

import pytest

from station.panel.history import unit_history
from station.records import open_records


def test_runs_and_trend_of_one_unit(tmp_path, session_factory):
    db = f"sqlite:///{tmp_path / 'r.db'}"
    mine = [session_factory(seed=s, serial="UR5E-H")[0] for s in (1, 2)]
    with open_records(db) as rec:
        for s in [*mine, session_factory(seed=3, serial="OTHER")[0]]:
            rec.store_session(s)
    h = unit_history("UR5E-H", db)
    assert {r["session"] for r in h["runs"]} == {s["session"] for s in mine}
    for r in h["runs"]:
        src = next(s for s in mine if s["session"] == r["session"])
        assert r["verdict"] == ("PASS" if src["verdict"]["passed"] else "FAIL")
        assert r["rms_after_m"] == pytest.approx(src["result"]["residuals"]["rms_after_m"])
        assert r["report"] == f"/report/{r['session']}"
    j2 = h["trend"]["offset.j2"]
    assert [x["value"] for x in j2] == pytest.approx([s["result"]["parameters"]["offset.j2"]["value"] for s in mine])
    assert unit_history("NOBODY", db) == {"serial": "NOBODY", "runs": [], "trend": {}}
