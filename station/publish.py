"""Hand a finished session on: store its record in the records database, write its report.

The engine journals and tears down; it imports neither ``station.records`` nor ``station.report``. This glue
(used by ``station.run``/``station.resume``/``station.session``, ``station run``/``resume``/``demo`` and
``station jog``) takes the engine's outcome to both, so a verdict is only shown once the record is stored.

Store-and-forward: the database is checked (opened, schema ready, a write accepted) before the robot moves
(:func:`check_records`); a store that fails at the end leaves the outcome ``NOT STORED`` (exit 2, never PASS)
with the journal complete, and ``station records sync`` stores it later from the journal (idempotent)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def check_records(db: str | None) -> str:
    """Open the records database at ``db`` and prove it takes a write (a row inserted and rolled back):
    a bad URL, an unreachable server or a read-only database is one line (``RecordsError``/``ConfigError``)
    before anything moves. Returns the URL as shown (no password)."""
    from datetime import UTC, datetime

    from sqlalchemy.exc import SQLAlchemyError

    from station.records import RecordsError, open_records
    from station.records import schema as S

    records = open_records(db)
    try:
        with records.engine.connect() as conn:
            tx = conn.begin()
            try:
                conn.execute(S.schema_version.insert().values(version=-1, applied_utc=datetime.now(UTC),
                                                              note="station write check (rolled back)"))
            finally:
                tx.rollback()
    except SQLAlchemyError as e:
        text = str(getattr(e, "orig", None) or e).strip().splitlines()
        raise RecordsError(f"records database {records.url!r} does not take writes: "
                           f"{text[0] if text else type(e).__name__}") from None
    finally:
        records.close()
    return records.url


def store_record(record: dict, db: str | None) -> None:
    """Store one session record (idempotent by session id) in the records database at ``db`` (default:
    ``$STATION_DB``, else SQLite in ``$STATION_HOME``). Durable when it returns."""
    from station.records import open_records

    records = open_records(db)
    try:
        records.store_session(record)
    finally:
        records.close()


def write_report(record: dict, folder: Path) -> Path:
    from station.report import write_report as _write

    return Path(_write(record, folder))


def publish(out, *, db: str | None = None, store: bool = True, report: bool = True,
            log: Callable[[str], None] | None = None):
    """Store ``out.record`` (``store``) and write the report into ``out.folder`` (``report``); returns ``out``
    with ``stored``/``report`` set. A store that fails sets ``out.store_error`` and turns a completed outcome
    into an error (``NOT STORED``, exit 2; the journal is complete, ``station records sync`` stores it later);
    the report is written either way. For a session that already failed a store failure is only logged."""
    db = db if db is not None else getattr(out, "db", None)
    if store:
        try:
            store_record(out.record, db)
            out.stored = True
        except Exception as e:
            out.store_error = str(e) or type(e).__name__
            if out.error is None:
                out.status, out.error = "error", e
            elif log is not None:
                log(f"could not store the failed session: {e}")
    if report:
        try:
            out.report = write_report(out.record, out.folder)
        except Exception as e:
            if out.error is None:
                out.status, out.error = "error", e
            elif log is not None:
                log(f"could not write the report of the failed session: {e}")
    return out


def _plain(record: dict):
    """A record as JSON sees it (what the database gives back), to compare a stored record with a journal's."""
    import json

    return json.loads(json.dumps(record, default=str))


def sync_sessions(refs: list[str] | None, db: str | None, *, home: Path | None = None,
                  log: Callable[[str], None] | None = None) -> list[tuple[str, str]]:
    """``station records sync``: store sessions from their journals (store-and-forward; storing again is
    idempotent). ``refs``: session ids, folders or journals; none: every session under ``home/sessions``
    that has ended and is not in the database yet. ``db`` None: the URL each journal's header names (else the
    default). A session whose record in the database already equals its journal's is "already stored" (nothing
    written), named or not; one whose record differs (resumed since) is stored again ("updated"). Returns
    ``[(session, "stored" | "updated" | "already stored" | "error: ...")]``."""
    from station.engine.journal import JournalError, read_journal, torn_tail
    from station.engine.runner import find_session, station_home
    from station.engine.session_record import session_from_events
    from station.records import RecordNotFound, open_records

    log = log or (lambda text: None)
    if refs:
        journals = [find_session(r) for r in refs]
        explicit = True
    else:
        journals = sorted((home or station_home()).joinpath("sessions").glob("*/journal.jsonl"))
        explicit = False
    out: list[tuple[str, str]] = []
    for path in journals:
        try:
            header, events = read_journal(path)
        except JournalError as e:
            out.append((path.parent.name, f"error: {e}"))
            continue
        torn = torn_tail(path)
        if torn:
            log(f"station: warning: {torn}")
        ended = any(e.type == "end" for e in events)
        if not explicit and not ended:
            continue  # still running or resumable: stored when it ends
        url = db if db is not None else header.db
        try:
            with open_records(url) as rec:
                record = session_from_events(header, events)
                try:
                    held = rec.session(header.session)
                except RecordNotFound:
                    held = None
                if held is not None and _plain(held) == _plain(record):
                    out.append((header.session, "already stored"))
                    continue
                rec.store_session(record)
            what = "stored" if held is None else "updated"
            out.append((header.session, what if ended else f"{what} (journal has no end: session open)"))
        except Exception as e:  # one line per session; the others are still tried
            out.append((header.session, f"error: {e}"))
    return out
