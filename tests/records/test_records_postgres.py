"""Records on a real PostgreSQL server (``pg_url`` fixture: $STATION_TEST_PG_URL or a throwaway cluster).
Serials and session ids are unique per run so a shared server's older data does not matter."""

from __future__ import annotations

import copy
import json
import threading
import uuid

import pytest

from station.records import RecordNotFound, SessionDataError, open_records

pytestmark = pytest.mark.postgres


def _canon(obj) -> str:
    """The session as the store keeps it: strict JSON, a NaN/Infinity (e.g. an unknown point's nominal) is null."""
    from station.safeio import dumps_json

    return json.dumps(json.loads(dumps_json(obj, compact=True, default=str)), sort_keys=True)


@pytest.fixture
def tag():
    return uuid.uuid4().hex[:10]


def test_postgres_round_trip_upsert_and_queries(pg_url, session_factory, tag):
    serial = f"PG-{tag}"
    with open_records(pg_url) as rec:
        assert rec.engine.dialect.name == "postgresql"
        full, _ = session_factory(seed=20, serial=serial, session_id=f"s1-{tag}")
        partial = copy.deepcopy(full)
        partial["samples"] = partial["samples"][:5]
        partial.update(result=None, verdict=None, writeback=None, finished=None)
        rec.store_session(partial)
        rec.store_session(full)
        rec.store_session(full)
        rows = rec.sessions(serial)
        assert len(rows) == 1 and rows[0]["store_count"] == 3 and rows[0]["n_samples"] == len(full["samples"])
        assert _canon(rec.session(full["session"])) == _canon(full)  # NaN nominal of point.A: null

        second, _ = session_factory(seed=21, serial=serial, session_id=f"s2-{tag}")
        rec.store_session(second)
        assert [s["session"] for s in rec.sessions(serial)] == [full["session"], second["session"]]
        assert rec.latest_result(serial)["session"] == second["session"]
        robot = rec.robot(serial)
        assert robot["n_sessions"] == 2 and robot["model"] == "ur5e"
        with pytest.raises(RecordNotFound):
            rec.robot(f"PG-none-{tag}")

        bad = copy.deepcopy(second)
        bad["samples"][0]["q"][0] = float("inf")
        with pytest.raises(SessionDataError, match="not a finite number"):
            rec.store_session(bad)
        assert _canon(rec.session(second["session"])) == _canon(second)


def test_postgres_is_durable_across_connections(pg_url, session_factory, tag):
    s, _ = session_factory(seed=22, serial=f"PG-{tag}", session_id=f"d-{tag}")
    with open_records(pg_url) as rec:
        rec.store_session(s)
    with open_records(pg_url) as other:  # a new engine: what it reads was committed
        assert _canon(other.session(s["session"])) == _canon(s)


def test_postgres_two_stations_store_the_same_new_robot_at_once(pg_url, session_factory, tag):
    """Two stations record sessions of one robot simultaneously: the robot row is upserted, not duplicated."""
    serial = f"PG-{tag}"
    sessions = [session_factory(seed=30 + i, serial=serial, session_id=f"c{i}-{tag}")[0] for i in range(4)]
    errors: list[BaseException] = []
    barrier = threading.Barrier(len(sessions))

    def store(s):
        try:
            with open_records(pg_url) as rec:
                barrier.wait(timeout=30)
                rec.store_session(s)
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=store, args=(s,)) for s in sessions]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors, errors
    with open_records(pg_url) as rec:
        assert rec.robot(serial)["n_sessions"] == 4
        assert sorted(s["session"] for s in rec.sessions(serial)) == sorted(s["session"] for s in sessions)
