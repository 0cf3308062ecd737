"""Run a procedure on a robot with guaranteed teardown, then store the record and write the report.

Whatever happens inside the checklist (a fault, a bus error, Ctrl-C, SIGTERM), the robot is stopped and left
non-compliant, the fault is journaled, and the session record (projected from the journal) is stored, so a
resume can continue. A verdict is only returned once the record is durably stored."""

from __future__ import annotations

import contextlib
import getpass
import os
import platform
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from station.engine.cell import Cell, RefPoint, load_cell
from station.engine.journal import Journal, JournalError, read_journal
from station.engine.limits import load_limits
from station.engine.procedure import Procedure, ProcedureError, load_procedure
from station.engine.session import Session
from station.kinematics.collision import keep_out_to_doc
from station.robot.errors import ConfigError
from station.robot.protocol import adopt_serial


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C (teardown, journal, exit)."""


@dataclass
class Outcome:
    session: str
    folder: Path
    status: str  # "completed" | "error" | "interrupted"
    passed: bool | None  # the verdict (None when the run did not reach it)
    record: dict = field(repr=False, default_factory=dict)
    report: Path | None = None
    error: BaseException | None = field(repr=False, default=None)
    stored: bool = False

    @property
    def exit_code(self) -> int:
        if self.status == "interrupted":
            return 130
        if self.status != "completed" or self.passed is None:
            return 2
        return 0 if self.passed else 1


def station_home() -> Path:
    return Path(os.environ.get("STATION_HOME") or "./station-data")


def new_session_id(procedure: str, serial: str) -> str:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in serial) or "unknown"
    return f"{procedure}-{safe}-{stamp}"


def _versions() -> dict:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for pkg in ("station", "numpy", "scipy"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def _db_for_journal(db: str | None) -> str | None:
    """The records URL for the journal header, so resume stores where the run did, but never a password
    (a URL with one is left out; resume then needs --db or $STATION_DB)."""
    if not db:
        return None
    from urllib.parse import urlsplit

    try:
        return None if urlsplit(db).password else db
    except ValueError:
        return None


def _cell_from_header(d: dict | None) -> Cell | None:
    if not d:
        return None
    from station.engine.cell import keep_out_from_dict

    return Cell(d.get("path", "journal"), {p["label"]: RefPoint.from_dict(p) for p in d["points"]}, d.get("model"),
                d.get("tool"), keep_out_from_dict(d, "journal cell", 1.0, 1.0))  # SI; none journaled: the table


def _optional_cell(cell_path) -> Cell | None:
    from station.engine.cell import default_cell_path

    if cell_path:
        return load_cell(cell_path)
    p = default_cell_path()
    return load_cell(p) if p.exists() else None


def _find_session(ref: str | Path) -> Path:
    p = Path(ref)
    for cand in (p, p / "journal.jsonl", station_home() / "sessions" / str(ref) / "journal.jsonl"):
        if cand.is_file():
            return cand
    raise ConfigError(f"session {ref!r}: no journal at {p} nor in {station_home() / 'sessions'}")


def create_session(robot, serial: str, *, procedure: Procedure | None = None, name: str | None = None,
                   sha256: str | None = None, path: str | None = None, title: str = "",
                   limits: str | Path | None = None, db: str | None = None, apply: bool = False,
                   cell: str | Path | Cell | None = None, operator: str | None = None, options: dict | None = None,
                   touch=None, progress: Callable[[int, int, str], None] | None = None,
                   log: Callable[[str], None] | None = None, robot_url: str = "") -> Session:
    """A new session on a connected robot: checks serial and limits, writes the journal header."""
    from station.engine.session import _identity_dict

    name = procedure.name if procedure else (name or "script")
    lim = load_limits(limits)  # bad files fail before anything moves
    the_cell = cell if isinstance(cell, Cell) else _optional_cell(cell)
    if not serial or not str(serial).strip():
        raise ConfigError("--serial is required: the record is filed under the robot's serial number")
    ident = adopt_serial(robot.identity(), str(serial))  # the wrong robot fails here, before anything is journaled
    try:
        table = lim.for_procedure(robot.model.name, name)
    except ConfigError:
        if procedure is not None:
            raise
        table = {}  # a script without its own limits section: measurements are informational
    opts = {**(procedure.defaults if procedure else {}), **(options or {}), "apply": bool(apply)}
    if isinstance(touch, str):
        opts["touch"] = touch
    sid = new_session_id(name, str(serial))
    folder = station_home() / "sessions" / sid
    header = {
        "session": sid, "procedure": name,
        "procedure_path": str(procedure.path.resolve()) if procedure else path,
        "procedure_sha256": procedure.sha256 if procedure else sha256,
        "procedure_title": procedure.title if procedure else title, "serial": str(serial),
        "operator": operator or getpass.getuser(), "station": socket.gethostname(),
        "url": robot_url or getattr(robot, "url", "") or ident.url,
        "model": robot.model.name, "robot": _identity_dict(ident),
        "limits": {"path": lim.path, "version": lim.version, "sha256": lim.sha256},
        "cell": None if the_cell is None else {"path": the_cell.path, "model": the_cell.model, "tool": the_cell.tool,
                                               "points": [p.to_dict() for p in the_cell.points.values()],
                                               **keep_out_to_doc(the_cell.keep_out)},
        "options": opts, "db": _db_for_journal(db), "versions": _versions(),
    }
    journal = Journal.create(folder / "journal.jsonl", header)
    return Session(journal, robot, limits=table, limits_version=lim.version, cell=the_cell, options=opts,
                   progress=progress, touch=None if isinstance(touch, str) else touch, log=log)


def start(procedure: str | Path | Procedure, robot_url: str, serial: str, *, limits: str | Path | None = None,
          db: str | None = None, apply: bool = False, cell: str | Path | Cell | None = None,
          operator: str | None = None, options: dict | None = None, touch=None,
          progress: Callable[[int, int, str], None] | None = None, log: Callable[[str], None] | None = None,
          report: bool = True, robot=None) -> Outcome:
    """Start a new session of ``procedure`` on the robot at ``robot_url`` and run it to the end."""
    from station.robot import open_robot

    proc = procedure if isinstance(procedure, Procedure) else load_procedure(procedure)
    load_limits(limits)  # a bad limits or cell file fails before the robot is opened
    if cell is not None:
        load_cell(cell)
    robot = robot or open_robot(robot_url)
    try:
        s = create_session(robot, serial, procedure=proc, limits=limits, db=db, apply=apply, cell=cell,
                           operator=operator, options=options, touch=touch, progress=progress, log=log,
                           robot_url=robot_url)
    except BaseException:
        robot.close()
        raise
    return _execute(s, proc.checklist, db=db, report=report)


def resume(session_ref: str | Path, *, db: str | None = None, touch=None,
           progress: Callable[[int, int, str], None] | None = None, log: Callable[[str], None] | None = None,
           report: bool = True, robot=None) -> Outcome:
    """Continue an interrupted session: same procedure file (hash checked), same plan, recorded samples kept."""
    from station.robot import open_robot

    path = _find_session(session_ref)
    try:
        header, events = read_journal(path)
    except JournalError as e:
        raise ConfigError(str(e)) from None
    if any(e.get("type") == "end" and e.get("status") == "completed" for e in events):
        raise ConfigError(f"session {header.get('session')} already completed; start a new one with station run")
    if not header.get("procedure_path"):
        kind = header.get("procedure") or "this kind of session"
        raise ConfigError(f"session {header.get('session')} ({kind}) has no procedure file to resume; its samples "
                          f"are kept in {path} (use station solve on its samples.csv, or start a new session)")
    proc = load_procedure(header["procedure_path"])
    if proc.sha256 != header.get("procedure_sha256"):
        raise ProcedureError(f"procedure {proc.path} changed since session {header['session']} started "
                             "(sha256 differs); resuming would mix two procedures")
    lim_info = header.get("limits") or {}
    lim = load_limits(lim_info.get("path"))
    if lim.sha256 != lim_info.get("sha256"):
        raise ConfigError(f"limits file {lim.path} changed since session {header['session']} started")
    robot = robot or open_robot(header["url"])
    try:
        table = lim.for_procedure(robot.model.name, proc.name)
        journal = Journal.open(path)
    except BaseException:
        robot.close()
        raise
    opts = dict(header.get("options") or {})
    s = Session(journal, robot, limits=table, limits_version=lim.version, cell=_cell_from_header(header.get("cell")),
                options=opts, replay=events, progress=progress, touch=touch, log=log)
    s.event({"type": "resume", "samples_kept": len(s.samples()), "events_before": len(events)})
    return _execute(s, proc.checklist, db=db if db is not None else header.get("db"), report=report)


def _install_sigterm():
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise Terminated()

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:
        return None


def _execute(s: Session, body: Callable[[Session], None], *, db: str | None, report: bool,
             store: bool = True) -> Outcome:
    status, err = "completed", None
    old = _install_sigterm()
    try:
        try:
            body(s)
        except KeyboardInterrupt as e:
            status, err = "interrupted", e
        except Exception as e:
            status, err = "error", e
        return finish(s, status, err, db=db, report=report, store=store)
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


def finish(s: Session, status: str, err: BaseException | None, *, db: str | None, report: bool,
           store: bool = True) -> Outcome:
    """Teardown (stop, compliance off) whatever happened, journal the fault and the end, close, then store the
    record and write the report. Used by the runner and by scripted sessions."""
    try:
        problems = s.safe_state()  # first: the robot stops, whatever the journal can still do
        if err is not None:
            s.event({"type": "fault", "step": _failed_step(s), "error": type(err).__name__,
                     "message": str(err) or type(err).__name__, "teardown": problems})
        elif problems:
            s.event({"type": "fault", "step": "teardown", "error": "teardown", "message": "; ".join(problems)})
        s.event({"type": "end", "status": status,
                 "passed": None if s.verdict is None else bool(s.verdict["passed"])})
    finally:
        with contextlib.suppress(Exception):  # closing a dead connection must not hide the original outcome
            s.robot.close()
        s.journal.close()
    record = s.record_dict()
    out = Outcome(s.id, s.folder, status, None if s.verdict is None else bool(s.verdict["passed"]), record,
                  error=err)
    _write_samples_csv(s)
    try:
        if store:
            _store(record, db)
            out.stored = True
        if report:
            from station.report import write_report

            out.report = Path(write_report(record, s.folder))
    except Exception as e:
        if out.error is None:
            out.status, out.error = "error", e
        else:
            s.log(f"could not store/report the failed session: {e}")
    return out


def _failed_step(s: Session) -> str | None:
    for e in reversed(s.events("step")):
        if e.get("status") in ("start", "failed"):
            return e.get("name")
    return None


def _store(record: dict, db: str | None) -> None:
    from station.records import open_records

    records = open_records(db)
    try:
        records.store_session(record)
    finally:
        records.close()


def _write_samples_csv(s: Session) -> None:
    """``samples.csv`` next to the journal, the format ``station solve`` reads (a projection, rewritten whole)."""
    import csv

    smp = s.samples()
    units = ["rad" if j.revolute else "m" for j in s.model.joints]
    tmp = s.folder / "samples.csv.tmp"
    with open(tmp, "w", newline="") as fh:
        fh.write(f"# station samples: session {s.id}, model {s.model.name}; joints in rad (m if prismatic), "
                 "measured x,y,z in m; seq = journal sequence number, set = fit|holdout\n")
        w = csv.writer(fh)
        meas = bool(smp) and all(x.get("measured") is not None for x in smp)
        w.writerow([f"q{i + 1}[{u}]" for i, u in enumerate(units)] + ["point", "seq", "set"]
                   + (["x[m]", "y[m]", "z[m]"] if meas else []))
        for x in smp:
            w.writerow([repr(float(v)) for v in x["q"]] + [x["point"], x["seq"], x.get("set", "fit")]
                       + ([repr(float(v)) for v in x["measured"]] if meas else []))
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, s.folder / "samples.csv")


def wall() -> float:
    return time.time()
