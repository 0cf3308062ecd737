"""``station records sync``: what it says for each session (docs/cli.md): "stored" the first time, "already
stored" when the database holds exactly the journal's record (named or not; nothing is written), "updated"
when the journal has more than the stored record (a session resumed since)."""

from __future__ import annotations

from station.engine import events as ev
from station.engine.journal import Journal
from station.publish import sync_sessions
from station.records import open_records
from tests.records.test_records_cli import _write_journal


def test_sync_says_stored_already_stored_updated(tmp_path, session_factory):
    session, _ = session_factory(seed=21)
    folder = tmp_path / "home" / "sessions" / session["session"]
    folder.mkdir(parents=True)
    journal = _write_journal(folder, session)
    db = f"sqlite:///{tmp_path / 'r.db'}"
    sid = session["session"]
    assert sync_sessions([str(folder)], db) == [(sid, "stored")]
    assert sync_sessions([str(folder)], db) == [(sid, "already stored")]  # named: nothing written again
    assert sync_sessions(None, db, home=tmp_path / "home") == [(sid, "already stored")]
    with open_records(db) as rec:
        assert rec.sessions(session["serial"])[0]["store_count"] == 1
    with Journal.open(journal) as j:  # the journal gained an event the record does not have
        j.append(ev.Fault(step="later", error="DeviceFault", message="a fault journaled after the first store"))
    assert sync_sessions(None, db, home=tmp_path / "home") == [(sid, "updated")]
    assert sync_sessions([str(journal)], db) == [(sid, "already stored")]
