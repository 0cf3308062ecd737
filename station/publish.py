"""Hand a finished session on: store its record in the records database, write its report.

The engine journals and tears down; it imports neither ``station.records`` nor ``station.report``. This glue
(used by ``station.run``/``station.resume``/``station.session``, ``station run``/``resume``/``demo`` and
``station jog``) takes the engine's outcome to both, so a verdict is only shown once the record is stored."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


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
    with ``stored``/``report`` set. A failure turns a completed outcome into an error (the journal keeps
    everything; storing again later is idempotent); for a session that already failed it is only logged."""
    db = db if db is not None else getattr(out, "db", None)
    try:
        if store:
            store_record(out.record, db)
            out.stored = True
        if report:
            out.report = write_report(out.record, out.folder)
    except Exception as e:
        if out.error is None:
            out.status, out.error = "error", e
        elif log is not None:
            log(f"could not store/report the failed session: {e}")
    return out
