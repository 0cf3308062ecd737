"""Records on SQLite: round trip, idempotent upsert after resume, queries, bad input, durability."""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
import textwrap

import pytest
import sqlalchemy as sa

from station.records import RecordNotFound, RecordsError, SessionDataError, default_url, open_records
from station.records.schema import SCHEMA_VERSION
from station.robot.errors import ConfigError


def _canon(obj) -> str:
    """The session as the store keeps it: strict JSON, a NaN/Infinity (e.g. an unknown point's nominal) is null."""
    from station.safeio import dumps_json

    return json.dumps(json.loads(dumps_json(obj, compact=True, default=str)), sort_keys=True)


@pytest.fixture
def rec(tmp_path):
    r = open_records(f"sqlite:///{tmp_path / 'station.db'}")
    yield r
    r.close()


def test_round_trip_returns_the_session_as_given(rec, session_factory):
    s, _ = session_factory(seed=1)
    assert rec.store_session(s) == s["session"]
    back = rec.session(s["session"])
    assert _canon(back) == _canon(s)
    assert rec.schema_version() == SCHEMA_VERSION


def test_restore_after_resume_updates_never_duplicates(rec, session_factory):
    full, _ = session_factory(seed=2)
    partial = copy.deepcopy(full)
    partial["samples"] = partial["samples"][:7]
    partial.update(finished=None, result=None, verdict=None, writeback=None)
    rec.store_session(partial)
    first = rec.sessions(full["serial"])
    assert len(first) == 1 and first[0]["n_samples"] == 7 and first[0]["passed"] is None
    assert first[0]["rms_after_m"] is None

    rec.store_session(full)  # resumed and finished
    rec.store_session(full)  # stored twice (e.g. a retry after a timeout): still one record
    rows = rec.sessions(full["serial"])
    assert len(rows) == 1
    row = rows[0]
    assert row["n_samples"] == len(full["samples"]) and row["store_count"] == 3
    assert row["passed"] is True and row["finished"] == full["finished"]
    assert row["rms_after_m"] == pytest.approx(full["result"]["residuals"]["rms_after_m"])
    assert row["stored"] == first[0]["stored"]  # first store time kept
    assert _canon(rec.session(full["session"])) == _canon(full)
    with rec.engine.connect() as c:
        n = c.execute(sa.text("SELECT count(*) FROM samples WHERE session_id = :s"), {"s": full["session"]}).scalar()
        p = c.execute(sa.text("SELECT count(*) FROM result_parameters WHERE session_id = :s"),
                      {"s": full["session"]}).scalar()
        w = c.execute(sa.text("SELECT count(*) FROM writeback_values WHERE session_id = :s"),
                      {"s": full["session"]}).scalar()
    assert (n, p, w) == (len(full["samples"]), len(full["result"]["parameters"]), 6)
    assert len(rec.robots()) == 1


def test_queries_by_serial_latest_result_history(rec, session_factory):
    a1, _ = session_factory(seed=3, serial="SN-A")
    a2, _ = session_factory(seed=4, serial="SN-A")
    b1, _ = session_factory(seed=5, serial="SN-B")
    a3, _ = session_factory(seed=6, serial="SN-A")
    a3.update(result=None, verdict=None, writeback=None)  # newest session aborted before the solve
    for s in (a2, b1, a3, a1):  # stored out of order
        rec.store_session(s)
    assert [s["session"] for s in rec.sessions("SN-A")] == [a1["session"], a2["session"], a3["session"]]
    assert [s["session"] for s in rec.sessions()] == [a1["session"], a2["session"], b1["session"], a3["session"]]
    assert rec.sessions("SN-NOPE") == []
    robots = {r["serial"]: r for r in rec.robots()}
    assert robots["SN-A"]["n_sessions"] == 3 and robots["SN-B"]["n_sessions"] == 1
    assert robots["SN-A"]["last_session"] == a3["session"]
    assert robots["SN-A"]["vendor"] == "Universal Robots" and robots["SN-A"]["identity"]["firmware"] == "5.15.0"

    latest = rec.latest_result("SN-A")
    assert latest["session"] == a2["session"]  # a3 has no result
    assert _canon(latest["result"]) == _canon(a2["result"])
    with pytest.raises(RecordNotFound, match="SN-NOPE"):
        rec.latest_result("SN-NOPE")
    with pytest.raises(RecordNotFound, match="nope"):
        rec.session("nope")

    hist = rec.parameter_history("SN-A", "offset.j2")
    assert [h["session"] for h in hist] == [a1["session"], a2["session"]]
    assert hist[0]["value"] == pytest.approx(a1["result"]["parameters"]["offset.j2"]["value"])
    assert hist[0]["std"] == pytest.approx(a1["result"]["parameters"]["offset.j2"]["std"])
    j6 = rec.parameter_history("SN-A", "offset.j6")
    assert j6[0]["identifiable"] is False and j6[0]["std"] is None

    meas = rec.measurements(a1["session"])
    assert [m["name"] for m in meas] == [m["name"] for m in a1["verdict"]["measurements"]]
    assert all(m["status"] in ("PASS", "MARGINAL") for m in meas)
    wb = {w["name"]: w for w in rec.writeback(a1["session"])}
    assert wb["offset.j2"]["before"] == pytest.approx(a1["writeback"]["before"]["offset.j2"])
    assert wb["offset.j2"]["after"] == pytest.approx(a1["writeback"]["after"]["offset.j2"])


def test_failed_verdict_and_marginal_are_recorded(rec, session_factory):
    s, _ = session_factory(seed=7, limit_mm=0.04)  # rms ~0.03-0.04 mm: close to or over the limit
    rec.store_session(s)
    statuses = {m["name"]: m["status"] for m in rec.measurements(s["session"])}
    rms = s["verdict"]["measurements"][0]
    expect = "FAIL" if rms["value"] > 0.04 else ("MARGINAL" if rms["value"] > 0.04 - rms["marginal"] else "PASS")
    assert statuses["rms_after"] == expect
    assert rec.sessions(s["serial"])[0]["passed"] is s["verdict"]["passed"]


@pytest.mark.parametrize("mutate, message", [
    (lambda s: s.pop("serial"), "'serial' is missing"),
    (lambda s: s.update(session=""), "session id"),
    (lambda s: s["samples"][3]["q"].__setitem__(2, math.nan), r"sample seq 16: q\[2\] is not a finite"),
    (lambda s: s["samples"][1].update(seq=s["samples"][0]["seq"]), "appears twice"),
    (lambda s: s.update(started="yesterday"), "not an ISO 8601 time"),
    (lambda s: s["robot"].update(serial="OTHER"), "identifies as 'OTHER'"),
    (lambda s: s.update(result=[1, 2]), "'result' must be a dict"),
])
def test_bad_session_dicts_raise_and_keep_the_record(rec, session_factory, mutate, message):
    good, _ = session_factory(seed=8)
    rec.store_session(good)
    bad = copy.deepcopy(good)
    mutate(bad)
    with pytest.raises(SessionDataError, match=message) as ei:
        rec.store_session(bad)
    assert "\n" not in str(ei.value)
    assert isinstance(ei.value, ValueError)
    assert _canon(rec.session(good["session"])) == _canon(good)  # nothing recorded is lost
    assert len(rec.sessions()) == 1


def test_session_cannot_move_to_another_serial(rec, session_factory):
    s, _ = session_factory(seed=9, serial="SN-1")
    rec.store_session(s)
    moved = copy.deepcopy(s)
    moved["serial"] = moved["robot"]["serial"] = "SN-2"
    with pytest.raises(SessionDataError, match="recorded for serial 'SN-1'"):
        rec.store_session(moved)
    assert [r["serial"] for r in rec.robots()] == ["SN-1"]


@pytest.mark.parametrize("url, kind, message", [
    ("nonsense", ConfigError, "bad database URL"),
    ("mysql://u@localhost/db", ConfigError, "only sqlite"),
    ("postgresql+psycopg://station@127.0.0.1:1/none", RecordsError, "cannot open records database"),
])
def test_bad_urls_give_one_line_errors(url, kind, message):
    with pytest.raises(kind, match=message) as ei:
        open_records(url)
    assert "\n" not in str(ei.value)


def test_password_is_not_shown(tmp_path):
    with pytest.raises(RecordsError) as ei:
        open_records("postgresql://station:s3cret@127.0.0.1:1/none")
    assert "s3cret" not in str(ei.value)


def test_default_url_uses_station_home(tmp_path, monkeypatch):
    monkeypatch.delenv("STATION_DB", raising=False)
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    assert default_url() == f"sqlite:///{tmp_path / 'home' / 'station.db'}"
    with open_records() as r:
        assert r.sessions() == []
    assert (tmp_path / "home" / "station.db").is_file()
    monkeypatch.setenv("STATION_DB", f"sqlite:///{tmp_path / 'other.db'}")
    assert default_url() == f"sqlite:///{tmp_path / 'other.db'}"


def test_newer_schema_is_refused(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    with open_records(url) as r, r.engine.begin() as c:
        c.execute(sa.text("INSERT INTO station_schema (version, applied_utc, note) "
                          "VALUES (:v, CURRENT_TIMESTAMP, 'future')"), {"v": SCHEMA_VERSION + 1})
    with pytest.raises(RecordsError, match=f"schema version {SCHEMA_VERSION + 1}, newer"):
        open_records(url)


def test_stored_session_survives_kill_9_right_after_store(tmp_path, session_factory):
    """Durable when store_session returns: the writer is killed with SIGKILL immediately afterwards."""
    s, _ = session_factory(seed=10)
    path = tmp_path / "session.json"
    path.write_text(json.dumps(s, allow_nan=True))
    url = f"sqlite:///{tmp_path / 'station.db'}"
    code = textwrap.dedent(f"""
        import json, os, signal
        from station.records import open_records
        r = open_records({url!r})
        r.store_session(json.loads(open({str(path)!r}).read()))
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert out.returncode == -9, out.stderr.decode()
    with open_records(url) as r:
        assert _canon(r.session(s["session"])) == _canon(s)


def test_version_1_database_is_migrated_without_loss(tmp_path, session_factory):
    """A database written by schema version 1 (no sessions.status, no samples.t_read) is upgraded in place when
    opened."""
    url = f"sqlite:///{tmp_path / 'old.db'}"
    s, _ = session_factory(seed=14)
    with open_records(url) as r:
        r.store_session(s)
        with r.engine.begin() as c:  # turn it back into what version 1 left on disk
            c.execute(sa.text("ALTER TABLE sessions DROP COLUMN status"))
            c.execute(sa.text("ALTER TABLE samples DROP COLUMN t_read"))
            c.execute(sa.text("UPDATE station_schema SET version = 1"))
    with open_records(url) as r:
        assert r.schema_version() == SCHEMA_VERSION == 3
        assert _canon(r.session(s["session"])) == _canon(s)
        assert r.sessions()[0]["status"] is None
        s2 = {**copy.deepcopy(s), "status": "passed"}
        r.store_session(s2)
        assert r.sessions()[0]["status"] == "passed"
        with r.engine.connect() as c:
            notes = c.execute(sa.text("SELECT version, note FROM station_schema ORDER BY version")).all()
    assert [tuple(n) for n in notes] == [(1, "created"), (2, "migrated from 1"), (3, "migrated from 2")]


def test_sample_reading_time_and_journal_time_are_kept_apart(tmp_path, session_factory):
    """Journal /2: ``t`` is when a sample was journaled, ``t_read`` when the joints were read."""
    s, _ = session_factory(seed=15)
    for i, smp in enumerate(s["samples"]):
        smp["t_read"] = smp["t"] - 0.25 - i * 1e-3
    with open_records(f"sqlite:///{tmp_path / 'r.db'}") as r:
        r.store_session(s)
        with r.engine.connect() as c:
            rows = c.execute(sa.text("SELECT t, t_read FROM samples ORDER BY seq")).all()
    assert [(a, b) for a, b in rows] == [(x["t"], x["t_read"]) for x in s["samples"]]
