"""Calibration records in a database (SQLAlchemy): SQLite file by default, PostgreSQL by URL.

Per robot serial: sessions, samples, results with uncertainties, verdicts, who/when/which station, and the
before/after values of anything written back. Input is the plain session dict of docs/architecture.md."""

from station.records.store import (
    RecordNotFound,
    Records,
    RecordsError,
    SessionDataError,
    default_url,
    open_records,
)
from station.records.verdict import measurement_status, overall_status

__all__ = ["RecordNotFound", "Records", "RecordsError", "SessionDataError", "default_url", "measurement_status",
           "open_records", "overall_status"]
