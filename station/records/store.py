"""``open_records(url)`` and ``Records``: store sessions idempotently, query them by serial and id.

A session is stored in one transaction: the robot and session rows are upserted by key and the session's
child rows (samples, parameters, measurements, written-back values) are replaced, so storing again after a
resume updates the record and never duplicates it. The commit is durable when ``store_session`` returns
(SQLite runs with ``synchronous=FULL``; PostgreSQL commits synchronously by default)."""

from __future__ import annotations

import json
import math
import os
from datetime import UTC, datetime
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy import event, func, select
from sqlalchemy.engine import URL, Connection, Engine, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, NoSuchModuleError, SQLAlchemyError

from station.records import schema as S
from station.records.verdict import finite_or_none as _float
from station.records.verdict import measurement_status
from station.robot.errors import ConfigError, StationError
from station.safeio import dumps_json


class RecordsError(StationError):
    """The records database cannot be opened or used (bad URL, server unreachable, newer schema)."""


class RecordNotFound(RecordsError):
    """No record for the serial or session id asked for."""


class SessionDataError(RecordsError, ValueError):
    """The session dict to store is malformed (missing keys, NaN joint values, a serial mix-up)."""


def default_url() -> str:
    """``$STATION_DB``, else ``sqlite:///$STATION_HOME/station.db`` (``STATION_HOME`` defaults to ./station-data)."""
    env = os.environ.get("STATION_DB")
    if env:
        return env
    home = Path(os.environ.get("STATION_HOME") or "station-data")
    return f"sqlite:///{home / 'station.db'}"


def _parse_url(text: str) -> URL:
    try:
        url = make_url(text)
    except ArgumentError:
        raise ConfigError(f"bad database URL {text!r}: expected e.g. sqlite:///station.db or "
                          "postgresql+psycopg://user@host/db") from None
    # psycopg (3) is the driver we ship; plain postgresql:// would ask for psycopg2
    if url.drivername in ("postgresql", "postgres"):
        url = url.set(drivername="postgresql+psycopg")
    if url.get_backend_name() not in ("sqlite", "postgresql"):
        raise ConfigError(f"bad database URL {url.render_as_string(hide_password=True)!r}: "
                          "only sqlite:/// and postgresql+psycopg:// are supported")
    return url


def _first_line(e: BaseException) -> str:
    text = str(getattr(e, "orig", None) or e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def open_records(url: str | None = None) -> Records:
    """Open (and create if missing) the records database at ``url`` (default: :func:`default_url`)."""
    text = url or default_url()
    parsed = _parse_url(text)
    shown = parsed.render_as_string(hide_password=True)
    kw: dict = {"future": True}
    if parsed.get_backend_name() == "sqlite":
        db = parsed.database
        if db and db != ":memory:" and not db.startswith("file:"):
            Path(db).expanduser().parent.mkdir(parents=True, exist_ok=True)
        kw["connect_args"] = {"timeout": 30}
    else:
        kw["pool_pre_ping"] = True
        kw["connect_args"] = {"connect_timeout": 10}
    try:
        engine = sa.create_engine(parsed, **kw)
    except (NoSuchModuleError, ArgumentError, ImportError) as e:
        raise ConfigError(f"bad database URL {shown!r}: {_first_line(e)}") from None
    if parsed.get_backend_name() == "sqlite":
        event.listen(engine, "connect", _sqlite_pragmas)
    records = Records(engine, shown)
    try:
        records._prepare()
    except SQLAlchemyError as e:
        engine.dispose()
        raise RecordsError(f"cannot open records database {shown!r}: {_first_line(e)}") from None
    except RecordsError:
        engine.dispose()
        raise
    return records


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=FULL")
    cur.close()


# ---- JSON helpers --------------------------------------------------------------------------------------
def _jsonable(o):
    try:
        import numpy as np
    except ImportError:  # pragma: no cover - numpy is a dependency
        np = None
    if np is not None:
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
    if isinstance(o, (tuple, set, frozenset)):
        return list(o)
    if isinstance(o, datetime):
        return o.isoformat()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _dumps(obj) -> str:
    # strict JSON (a PostgreSQL json column, a report or any other reader takes it): a NaN/inf (e.g. the
    # condition number of a rank-deficient solve) is stored as null, as the result file writes it
    return dumps_json(obj, compact=True, default=_jsonable)


def _loads(text: str | None):
    return None if text is None else json.loads(text)


def _time(text, what: str) -> datetime | None:
    if text in (None, ""):
        return None
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return datetime.fromtimestamp(float(text), UTC)
    try:
        t = datetime.fromisoformat(str(text))
    except ValueError:
        raise SessionDataError(f"{what}: {text!r} is not an ISO 8601 time") from None
    return t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)


def _iso(t: datetime | None) -> str | None:
    if t is None:
        return None
    if t.tzinfo is None:  # SQLite returns naive datetimes; they were stored as UTC
        t = t.replace(tzinfo=UTC)
    return t.isoformat()


# ---- validation ----------------------------------------------------------------------------------------
def _finite_list(values, what: str, *, allow_none: bool = False) -> list[float] | None:
    if values is None:
        if allow_none:
            return None
        raise SessionDataError(f"{what}: missing")
    try:
        seq = [float(v) for v in list(values)]
    except (TypeError, ValueError):
        raise SessionDataError(f"{what}: expected a list of numbers, got {values!r}") from None
    for i, v in enumerate(seq):
        if not math.isfinite(v):
            raise SessionDataError(f"{what}[{i}] is not a finite number ({v})")
    return seq


def _check_session(session) -> tuple[str, str]:
    if not isinstance(session, dict):
        raise SessionDataError(f"session record must be a dict, got {type(session).__name__}")
    sid, serial = session.get("session"), session.get("serial")
    if not isinstance(sid, str) or not sid.strip():
        raise SessionDataError("session record: 'session' (the session id) is missing or empty")
    if not isinstance(serial, str) or not serial.strip():
        raise SessionDataError(f"session {sid}: 'serial' is missing or empty")
    for key in ("result", "verdict", "writeback", "robot"):
        if session.get(key) is not None and not isinstance(session[key], dict):
            raise SessionDataError(f"session {sid}: {key!r} must be a dict or null")
    if not isinstance(session.get("samples") or [], list):
        raise SessionDataError(f"session {sid}: 'samples' must be a list")
    return sid, serial


class Records:
    """A records database. Use :func:`open_records`; close with :meth:`close` or a ``with`` block."""

    def __init__(self, engine: Engine, shown_url: str) -> None:
        self.engine = engine
        self.url = shown_url  # password hidden

    def __enter__(self) -> Records:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.engine.dispose()

    # ---- schema --------------------------------------------------------------------------------------
    def _prepare(self) -> None:
        try:
            S.metadata.create_all(self.engine)
        except DBAPIError:
            # another station created the tables at the same moment: the second look finds them
            S.metadata.create_all(self.engine)
        with self.engine.begin() as conn:
            version = conn.execute(select(func.max(S.schema_version.c.version))).scalar()
            if version is None:
                conn.execute(S.schema_version.insert().values(
                    version=S.SCHEMA_VERSION, applied_utc=datetime.now(UTC), note="created"))
                return
            if version > S.SCHEMA_VERSION:
                raise RecordsError(f"records database {self.url!r} has schema version {version}, newer than "
                                   f"this station understands ({S.SCHEMA_VERSION}); update the station software")
            for v in range(version, S.SCHEMA_VERSION):
                S.MIGRATIONS[v](conn)
                conn.execute(S.schema_version.insert().values(
                    version=v + 1, applied_utc=datetime.now(UTC), note=f"migrated from {v}"))

    def schema_version(self) -> int:
        with self.engine.connect() as conn:
            return int(conn.execute(select(func.max(S.schema_version.c.version))).scalar() or 0)

    # ---- store ---------------------------------------------------------------------------------------
    def store_session(self, session: dict) -> str:
        """Insert or update the session (keyed by ``session["session"]``) in one transaction; returns its id.

        Durable when it returns. Raises :class:`SessionDataError` for a malformed dict (nothing is written)."""
        sid, serial = _check_session(session)
        rows = self._rows(session, sid, serial)
        try:
            with self.engine.begin() as conn:
                self._store(conn, sid, serial, rows)
        except SQLAlchemyError as e:
            raise RecordsError(f"storing session {sid} in {self.url!r} failed: {_first_line(e)}") from None
        return sid

    def _rows(self, session: dict, sid: str, serial: str) -> dict:
        now = datetime.now(UTC)
        robot = dict(session.get("robot") or {})
        result = session.get("result")
        verdict = session.get("verdict")
        writeback = session.get("writeback")
        residuals = (result or {}).get("residuals") or {}
        doc = {k: v for k, v in session.items() if k != "samples"}
        sample_rows = _sample_rows(session.get("samples") or [], sid)
        param_rows = _param_rows(result, sid)
        meas_rows = _measurement_rows(verdict, sid)
        wb_rows = _writeback_rows(writeback, sid)
        passed = (verdict or {}).get("passed")
        session_row = {
            "id": sid, "serial": serial, "procedure": str(session.get("procedure") or ""),
            "procedure_sha256": str(session.get("procedure_sha256") or ""),
            "station": str(session.get("station") or ""), "operator": str(session.get("operator") or ""),
            "model": str(session.get("model") or robot.get("model") or ""),
            "started": str(session.get("started") or ""),
            "finished": None if session.get("finished") is None else str(session["finished"]),
            "started_utc": _time(session.get("started"), f"session {sid}: started"),
            "finished_utc": _time(session.get("finished"), f"session {sid}: finished"),
            "passed": None if passed is None else bool(passed), "n_samples": len(sample_rows),
            "status": None if session.get("status") is None else str(session["status"])[:32],
            "converged": None if result is None or result.get("converged") is None else bool(result["converged"]),
            "rank": (result or {}).get("rank"), "n_parameters": (result or {}).get("n_parameters"),
            "rms_before_m": _float(residuals.get("rms_before_m")), "rms_after_m": _float(residuals.get("rms_after_m")),
            "max_after_m": _float(residuals.get("max_after_m")),
            "writeback_applied": None if not writeback else bool(writeback.get("applied")),
            "writeback_verified": None if not writeback else bool(writeback.get("verified")),
            "doc_json": _dumps(doc), "stored_utc": now, "updated_utc": now, "store_count": 1}
        robot_row = {
            "serial": serial, "vendor": str(robot.get("vendor") or ""), "model": str(robot.get("model") or
                                                                                      session.get("model") or ""),
            "firmware": str(robot.get("firmware") or ""), "url": str(robot.get("url") or ""),
            "identity_json": _dumps(robot), "first_seen_utc": now, "last_seen_utc": now}
        if robot.get("serial") not in (None, "", serial):
            raise SessionDataError(f"session {sid}: serial {serial!r} but the robot identifies as "
                                   f"{robot['serial']!r}")
        return {"session": session_row, "robot": robot_row, "samples": sample_rows, "parameters": param_rows,
                "measurements": meas_rows, "writeback": wb_rows}

    def _store(self, conn: Connection, sid: str, serial: str, rows: dict) -> None:
        old = conn.execute(select(S.sessions.c.serial).where(S.sessions.c.id == sid)).scalar()
        if old is not None and old != serial:
            raise SessionDataError(f"session {sid} is recorded for serial {old!r}, not {serial!r}")
        self._upsert(conn, S.robots, rows["robot"], ["serial"], keep=["first_seen_utc"])
        self._upsert(conn, S.sessions, rows["session"], ["id"], keep=["stored_utc", "store_count"],
                     bump="store_count")
        for table in S.CHILD_TABLES:
            conn.execute(table.delete().where(table.c.session_id == sid))
        for table, key in ((S.samples, "samples"), (S.parameters, "parameters"),
                           (S.measurements, "measurements"), (S.writeback_values, "writeback")):
            if rows[key]:
                conn.execute(table.insert(), rows[key])

    @staticmethod
    def _upsert(conn: Connection, table: sa.Table, row: dict, keys: list[str], keep: list[str],
                bump: str | None = None) -> None:
        dialect = conn.dialect.name
        if dialect == "postgresql":
            from sqlalchemy.dialects.postgresql import insert
        else:
            from sqlalchemy.dialects.sqlite import insert
        stmt = insert(table).values(**row)
        update = {k: stmt.excluded[k] for k in row if k not in keys and k not in keep}
        if bump:
            update[bump] = table.c[bump] + 1
        conn.execute(stmt.on_conflict_do_update(index_elements=keys, set_=update))

    # ---- queries -------------------------------------------------------------------------------------
    def robots(self) -> list[dict]:
        """Every robot with its session count and latest session, ordered by serial."""
        s = S.sessions
        with self.engine.connect() as conn:
            counts = dict(conn.execute(select(s.c.serial, func.count()).group_by(s.c.serial)).all())
            out = []
            for r in conn.execute(select(S.robots).order_by(S.robots.c.serial)).mappings():
                last = conn.execute(select(s.c.id, s.c.started, s.c.passed).where(s.c.serial == r["serial"])
                                    .order_by(s.c.started_utc.desc(), s.c.updated_utc.desc()).limit(1)).first()
                out.append({"serial": r["serial"], "vendor": r["vendor"], "model": r["model"],
                            "firmware": r["firmware"], "url": r["url"], "identity": _loads(r["identity_json"]),
                            "first_seen": _iso(r["first_seen_utc"]), "last_seen": _iso(r["last_seen_utc"]),
                            "n_sessions": int(counts.get(r["serial"], 0)),
                            "last_session": last[0] if last else None, "last_started": last[1] if last else None,
                            "last_passed": last[2] if last else None})
        return out

    def robot(self, serial: str) -> dict:
        for r in self.robots():
            if r["serial"] == serial:
                return r
        raise RecordNotFound(f"no records for serial {serial!r} in {self.url}")

    def sessions(self, serial: str | None = None) -> list[dict]:
        """Session summaries (no samples), oldest first; for one serial when given (unknown serial: [])."""
        s = S.sessions
        q = select(s).order_by(s.c.started_utc, s.c.id)
        if serial is not None:
            q = q.where(s.c.serial == serial)
        with self.engine.connect() as conn:
            return [self._summary(r) for r in conn.execute(q).mappings()]

    @staticmethod
    def _summary(r) -> dict:
        return {"session": r["id"], "serial": r["serial"], "procedure": r["procedure"],
                "procedure_sha256": r["procedure_sha256"], "station": r["station"], "operator": r["operator"],
                "model": r["model"], "started": r["started"], "finished": r["finished"], "passed": r["passed"],
                "status": r["status"],
                "n_samples": r["n_samples"], "converged": r["converged"], "rank": r["rank"],
                "n_parameters": r["n_parameters"], "rms_before_m": r["rms_before_m"],
                "rms_after_m": r["rms_after_m"], "max_after_m": r["max_after_m"],
                "writeback_applied": r["writeback_applied"], "writeback_verified": r["writeback_verified"],
                "stored": _iso(r["stored_utc"]), "updated": _iso(r["updated_utc"]), "store_count": r["store_count"]}

    def session(self, session_id: str) -> dict:
        """The session dict as stored (same shape as given to :meth:`store_session`), samples in seq order."""
        with self.engine.connect() as conn:
            doc = conn.execute(select(S.sessions.c.doc_json).where(S.sessions.c.id == session_id)).scalar()
            if doc is None:
                raise RecordNotFound(f"no session {session_id!r} in {self.url}")
            out = _loads(doc)
            rows = conn.execute(select(S.samples.c.doc_json).where(S.samples.c.session_id == session_id)
                                .order_by(S.samples.c.seq)).scalars()
            out["samples"] = [_loads(t) for t in rows]
        return out

    def latest_result(self, serial: str) -> dict | None:
        """The newest session of ``serial`` that has a solver result: ``{"session", "started", "finished",
        "passed", "result"}``; None when none has one. Unknown serial: :class:`RecordNotFound`."""
        self.robot(serial)
        s = S.sessions
        with self.engine.connect() as conn:
            r = conn.execute(select(s.c.id, s.c.started, s.c.finished, s.c.passed, s.c.doc_json)
                             .where(s.c.serial == serial, s.c.n_parameters.is_not(None))
                             .order_by(s.c.started_utc.desc(), s.c.updated_utc.desc()).limit(1)).first()
        if r is None:
            return None
        return {"session": r[0], "started": r[1], "finished": r[2], "passed": r[3],
                "result": _loads(r[4]).get("result")}

    def parameter_history(self, serial: str, name: str) -> list[dict]:
        """One parameter of one robot over its sessions, oldest first: ``{"session", "started", "value",
        "std", "identifiable"}`` (SI)."""
        s, p = S.sessions, S.parameters
        q = (select(s.c.id, s.c.started, p.c.value, p.c.std, p.c.identifiable)
             .join(p, p.c.session_id == s.c.id).where(s.c.serial == serial, p.c.name == name)
             .order_by(s.c.started_utc, s.c.id))
        with self.engine.connect() as conn:
            return [{"session": r[0], "started": r[1], "value": r[2], "std": r[3], "identifiable": r[4]}
                    for r in conn.execute(q)]

    def measurements(self, session_id: str) -> list[dict]:
        """The verdict rows of a session with their PASS/FAIL/MARGINAL status."""
        m = S.measurements
        with self.engine.connect() as conn:
            return [dict(r) for r in conn.execute(
                select(m.c.name, m.c.value, m.c.unit, m.c.low, m.c.high, m.c.passed, m.c.status)
                .where(m.c.session_id == session_id).order_by(m.c.idx)).mappings()]

    def writeback(self, session_id: str) -> list[dict]:
        """Before/after values (SI) of everything written back in a session."""
        w = S.writeback_values
        with self.engine.connect() as conn:
            return [dict(r) for r in conn.execute(select(w.c.name, w.c.before, w.c.after)
                                                  .where(w.c.session_id == session_id).order_by(w.c.name))
                    .mappings()]


def _sample_rows(samples: list, sid: str) -> list[dict]:
    """One row per sample (sequence numbers unique, of this session; joint values finite)."""
    sample_rows, seen = [], set()
    for i, smp in enumerate(samples):
        if not isinstance(smp, dict):
            raise SessionDataError(f"session {sid}: sample {i} is not a dict")
        seq = smp.get("seq")
        if not isinstance(seq, int) or isinstance(seq, bool):
            raise SessionDataError(f"session {sid}: sample {i}: 'seq' must be an integer, got {seq!r}")
        if seq in seen:
            raise SessionDataError(f"session {sid}: sample seq {seq} appears twice")
        seen.add(seq)
        if smp.get("session") not in (None, sid):
            raise SessionDataError(f"session {sid}: sample seq {seq} belongs to session {smp['session']!r}")
        q = _finite_list(smp.get("q"), f"session {sid} sample seq {seq}: q")
        measured = _finite_list(smp.get("measured"), f"session {sid} sample seq {seq}: measured",
                                allow_none=True)
        pose = smp.get("pose")
        sample_rows.append({
            "session_id": sid, "seq": seq, "point": str(smp.get("point") or ""),
            "pose": int(pose) if isinstance(pose, (int, float)) and not isinstance(pose, bool) else None,
            "set": str(smp.get("set") or "fit"), "t": _float(smp.get("t")), "t_read": _float(smp.get("t_read")),
            "t_device": _float(smp.get("t_device")),
            "raw_unit": smp.get("raw_unit"), "q_json": _dumps(q),
            "measured_json": None if measured is None else _dumps(measured), "doc_json": _dumps(smp)})
    return sample_rows


def _param_rows(result: dict | None, sid: str) -> list[dict]:
    param_rows = []
    for name, p in ((result or {}).get("parameters") or {}).items():
        if not isinstance(p, dict):
            raise SessionDataError(f"session {sid}: result parameter {name!r} is not a dict")
        param_rows.append({
            "session_id": sid, "name": str(name), "value": _float(p.get("value")), "std": _float(p.get("std")),
            "nominal": _float(p.get("nominal")), "identifiable": bool(p.get("identifiable")),
            "reason": p.get("reason") or None, "kind": p.get("kind"), "unit": p.get("unit")})
    return param_rows


def _measurement_rows(verdict: dict | None, sid: str) -> list[dict]:
    meas_rows = []
    for i, m in enumerate((verdict or {}).get("measurements") or []):
        if not isinstance(m, dict) or not m.get("name"):
            raise SessionDataError(f"session {sid}: verdict measurement {i} has no name")
        meas_rows.append({
            "session_id": sid, "idx": i, "name": str(m["name"]), "value": _float(m.get("value")),
            "unit": m.get("unit"), "low": _float(m.get("low")), "high": _float(m.get("high")),
            "marginal_json": _dumps(m.get("marginal")),
            "passed": None if m.get("passed") is None else bool(m.get("passed")),
            "status": measurement_status(m)})
    return meas_rows


def _writeback_rows(writeback: dict | None, sid: str) -> list[dict]:
    """Each written parameter's value before and after."""
    wb_rows = []
    if writeback:
        before, after = writeback.get("before") or {}, writeback.get("after") or {}
        for name in list(dict.fromkeys([*before, *after])):
            wb_rows.append({"session_id": sid, "name": str(name), "before": _float(before.get(name)),
                            "after": _float(after.get(name))})
    return wb_rows
