"""The records tables (SQLAlchemy Core) and the schema version with its migrations.

One row per robot serial, per session, per sample, per identified parameter, per verdict measurement and per
written-back value. The session dict and each sample dict are also kept whole as JSON text so a stored
session reads back exactly as it was given; the columns are there to be queried.
Values are SI (m, rad); times are ISO 8601 text as the engine wrote them plus a UTC timestamp for ordering."""

from __future__ import annotations

from collections.abc import Callable

from sqlalchemy import (
    Boolean,
    Column,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    text,
)
from sqlalchemy.engine import Connection

SCHEMA_VERSION = 3

metadata = MetaData()

schema_version = Table(
    "station_schema", metadata,
    Column("version", Integer, primary_key=True),
    Column("applied_utc", DateTime(timezone=True), nullable=False),
    Column("note", Text, nullable=False, default=""),
)

robots = Table(
    "robots", metadata,
    Column("serial", String(128), primary_key=True),
    Column("vendor", String(128), nullable=False, default=""),
    Column("model", String(128), nullable=False, default=""),
    Column("firmware", String(128), nullable=False, default=""),
    Column("url", Text, nullable=False, default=""),
    Column("identity_json", Text, nullable=False, default="{}"),  # latest Identity as dict
    Column("first_seen_utc", DateTime(timezone=True), nullable=False),
    Column("last_seen_utc", DateTime(timezone=True), nullable=False),
)

sessions = Table(
    "sessions", metadata,
    Column("id", String(128), primary_key=True),
    Column("serial", String(128), ForeignKey("robots.serial"), nullable=False, index=True),
    Column("procedure", String(128), nullable=False, default=""),
    Column("procedure_sha256", String(64), nullable=False, default=""),
    Column("station", String(255), nullable=False, default=""),
    Column("operator", String(255), nullable=False, default=""),
    Column("model", String(128), nullable=False, default=""),
    Column("started", String(64), nullable=False, default=""),  # ISO text as given
    Column("finished", String(64)),
    Column("started_utc", DateTime(timezone=True), index=True),
    Column("finished_utc", DateTime(timezone=True)),
    Column("passed", Boolean),  # None: no verdict (yet)
    Column("status", String(32)),  # the engine's end status (passed, failed, error, aborted...); v2
    Column("n_samples", Integer, nullable=False, default=0),
    # result summary, SI; the whole CalibrationResult.to_dict() is in doc_json["result"]
    Column("converged", Boolean),
    Column("rank", Integer),
    Column("n_parameters", Integer),
    Column("rms_before_m", Float),
    Column("rms_after_m", Float),
    Column("max_after_m", Float),
    Column("writeback_applied", Boolean),
    Column("writeback_verified", Boolean),
    # the session dict as given without its samples (robot identity, result, verdict, write-back, extras)
    Column("doc_json", Text, nullable=False),
    Column("stored_utc", DateTime(timezone=True), nullable=False),  # first store
    Column("updated_utc", DateTime(timezone=True), nullable=False),  # last store (resume re-stores)
    Column("store_count", Integer, nullable=False, default=1),
)

samples = Table(
    "samples", metadata,
    Column("session_id", String(128), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("seq", Integer, primary_key=True),
    Column("point", String(64), nullable=False, default=""),
    Column("pose", Integer),
    Column("set", String(16), nullable=False, default="fit"),
    Column("t", Float),  # unix s, host clock: when the sample was journaled
    Column("t_device", Float),  # the device's own clock at the reading (s)
    Column("raw_unit", String(16)),
    Column("q_json", Text, nullable=False),  # SI joint values
    Column("measured_json", Text),  # [x, y, z] m in the instrument frame or null
    Column("doc_json", Text, nullable=False),  # the sample dict as given
    Column("t_read", Float),  # unix s, host clock: when the joints were read; v3 (null before)
)

parameters = Table(
    "result_parameters", metadata,
    Column("session_id", String(128), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("name", String(128), primary_key=True),
    Column("value", Float),  # SI
    Column("std", Float),  # SI; null when not identifiable
    Column("nominal", Float),
    Column("identifiable", Boolean, nullable=False),
    Column("reason", Text),
    Column("kind", String(32)),
    Column("unit", String(8)),
)

measurements = Table(
    "verdict_measurements", metadata,
    Column("session_id", String(128), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("idx", Integer, primary_key=True),
    Column("name", String(128), nullable=False),
    Column("value", Float),
    Column("unit", String(32)),
    Column("low", Float),
    Column("high", Float),
    Column("marginal_json", Text),  # as given: a band width or a flag
    Column("passed", Boolean),
    Column("status", String(16), nullable=False),  # PASS | FAIL | MARGINAL
)

writeback_values = Table(
    "writeback_values", metadata,
    Column("session_id", String(128), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("name", String(128), primary_key=True),
    Column("before", Float),  # SI, what the device held before the write (the pre-image)
    Column("after", Float),  # SI, what it holds now (read back)
)

CHILD_TABLES = (samples, parameters, measurements, writeback_values)

# Migrations: version N -> N+1, each run inside the opening transaction. Additive only (new tables, new
# nullable columns); a database newer than this code is refused rather than guessed at.
def _v1_to_v2(conn: Connection) -> None:
    conn.execute(text("ALTER TABLE sessions ADD COLUMN status VARCHAR(32)"))


def _v2_to_v3(conn: Connection) -> None:
    # journal /2 separates a sample's reading time (t_read) from its append time (t)
    conn.execute(text("ALTER TABLE samples ADD COLUMN t_read FLOAT"))


MIGRATIONS: dict[int, Callable[[Connection], None]] = {1: _v1_to_v2, 2: _v2_to_v3}
