"""``station records list`` at 80 columns, ``records show --trend`` (drift beyond 3 sigma) and ``records export``
against a real SQLite records database filled with fitted sessions (conftest ``session_factory``)."""

from __future__ import annotations

import copy
import csv
import io
import json
import math

import pytest
from clirunner import station_main

from station.records import open_records

LONG = "OMX-2026-LINE3-000000004217"  # longer than rich would leave a column at 80 columns


def _shifted(session: dict, name: str, n_sigma: float, seed: int) -> dict:
    """A copy of ``session`` (new id, later start) whose ``name`` moved by ``n_sigma`` of its own std."""
    s = copy.deepcopy(session)
    p = s["result"]["parameters"][name]
    p["value"] += n_sigma * p["std"]
    s["session"] = f"20261121-{seed:04d}-{s['serial']}"
    s["started"] = s["started"].replace("T08:0", "T09:0")
    s["finished"] = s["finished"].replace("T08:", "T09:")
    for x in s["samples"]:
        x["session"] = s["session"]
    return s


@pytest.fixture
def db(tmp_path, session_factory):
    url = f"sqlite:///{tmp_path / 'station.db'}"
    with open_records(url) as rec:
        for seed in (1, 2, 3):
            rec.store_session(session_factory(seed=seed, serial=LONG)[0])
        last = session_factory(seed=3, serial=LONG)[0]
        rec.store_session(_shifted(last, "offset.j2", 20.0, seed=4))
        rec.store_session(session_factory(seed=5, serial="UR5E-B", limit_mm=1e-6)[0])  # a FAIL
    return url


def test_list_at_80_columns_keeps_serial_and_verdict(db, session_factory):
    code, out, _ = station_main("records", "list", "--db", db, columns=80)
    assert code == 0, out
    assert max(len(line) for line in out.splitlines()[1:]) <= 80, out  # (title line names the db path)
    rows = {line.split()[0]: line for line in out.splitlines() if line.strip().startswith((LONG, "UR5E-B"))}
    assert LONG in rows and "PASS" in rows[LONG], out
    assert "FAIL" in rows["UR5E-B"], out
    code, out, _ = station_main("records", "list", "--db", db, "--serial", LONG, columns=80)
    assert code == 0, out
    assert all(len(line) <= 80 for line in out.splitlines()[1:]), out
    for seed in (1, 2, 3):
        sid = session_factory(seed=seed, serial=LONG)[0]["session"]
        line = next(iter(x for x in out.splitlines() if sid in x))
        assert "PASS" in line, out


def test_trend_flags_the_moved_parameter_only(db, session_factory):
    code, out, _ = station_main("records", "show", LONG, "--db", db, "--trend", columns=120)
    assert code == 0, out
    # independent computation of the flagged change
    a = session_factory(seed=3, serial=LONG)[0]["result"]["parameters"]["offset.j2"]
    b = _shifted(session_factory(seed=3, serial=LONG)[0], "offset.j2", 20.0, 4)["result"]["parameters"]["offset.j2"]
    ratio = abs(b["value"] - a["value"]) / math.hypot(a["std"], b["std"])
    drift_lines = [line for line in out.splitlines() if "DRIFT" in line]
    assert len(drift_lines) == 1 and f"{ratio:.1f}" in drift_lines[0], out
    assert "1 drift(s) beyond 3 σ" in out
    # the value is shown in deg with its uncertainty
    assert f"{math.degrees(b['value']):.4f}" in drift_lines[0] and f"{math.degrees(b['std']):.4f}" in drift_lines[0]


def test_trend_of_repeat_runs_without_change_has_no_drift(tmp_path, session_factory):
    url = f"sqlite:///{tmp_path / 'r.db'}"
    with open_records(url) as rec:
        for seed in (11, 12, 13):  # the same hidden truth, independent noise
            rec.store_session(session_factory(seed=seed, serial="SAME")[0])
    code, out, _ = station_main("records", "show", "SAME", "--db", url, "--trend", columns=120)
    assert code == 0 and "no drift beyond 3 σ" in out and "DRIFT" not in out, out


def test_export_csv_and_json_since(db, session_factory):
    code, out, _ = station_main("records", "export", "--db", db, "--format", "csv", "--since",
                                  "2026-11-21T08:02:00Z", columns=80)
    assert code == 0, out
    rows = list(csv.DictReader(io.StringIO(out)))
    sessions = {r["session"] for r in rows}
    s1, s2 = (session_factory(seed=k, serial=LONG)[0] for k in (1, 2))
    assert s1["session"] not in sessions and s2["session"] in sessions  # started 08:01 vs 08:02
    r = next(r for r in rows if r["session"] == s2["session"] and r["parameter"] == "offset.j3")
    assert float(r["value"]) == pytest.approx(s2["result"]["parameters"]["offset.j3"]["value"], rel=1e-12)
    assert r["unit"] == "rad" and r["verdict"] == "PASS" and r["serial"] == LONG
    assert {x["verdict"] for x in rows if x["serial"] == "UR5E-B"} == {"FAIL"}
    code, out, _ = station_main("records", "export", "--db", db, "--format", "json", "--serial", LONG, columns=80)
    assert code == 0, out
    doc = json.loads(out)
    assert doc["units"].startswith("SI") and len(doc["sessions"]) == 4
    assert doc["sessions"][0]["parameters"]["offset.j2"]["std"] == pytest.approx(
        s1["result"]["parameters"]["offset.j2"]["std"])


@pytest.mark.parametrize("args, message", [
    (["--format", "xml"], "--format must be csv or json"),
    (["--since", "yesterday"], "--since 'yesterday' is not an ISO date"),
])
def test_export_bad_input_one_line_exit_2(db, args, message):
    result = station_main("records", "export", "--db", db, *args, columns=80)
    assert result.code == 2 and not result.out
    lines = result.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: ") and message in lines[0], result.err
