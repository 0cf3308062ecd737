"""Run a procedure on a robot with guaranteed teardown; the outcome carries the session record.

Whatever happens inside the checklist (a fault, a bus error, Ctrl-C, SIGTERM), the robot is stopped and left
non-compliant, the fault and the end are journaled and ``samples.csv`` is written, so a resume can continue.
The engine stores nothing in the records database and writes no report: the caller hands the outcome on
(``station.publish.publish``, used by ``station.run``/``station resume``/the CLI), and shows a verdict only
once the record is stored."""

from __future__ import annotations

import contextlib
import getpass
import os
import platform
import signal
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from station.engine import events as ev
from station.engine.cell import Cell, RefPoint, load_cell
from station.engine.journal import Journal, JournalError, read_journal
from station.engine.limits import load_limits
from station.engine.procedure import Procedure, ProcedureError, load_procedure
from station.engine.session import Session
from station.kinematics.collision import keep_out_to_doc
from station.robot.errors import ConfigError
from station.robot.protocol import adopt_serial
from station.samplesfile import joint_units, write_samples_csv


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C (teardown, journal, exit)."""


@dataclass
class Outcome:
    session: str
    folder: Path
    status: str  # "completed" | "error" | "interrupted"
    passed: bool | None  # the verdict (None when the run did not reach it, or there were no limits)
    record: dict = field(repr=False, default_factory=dict)
    report: Path | None = None
    error: BaseException | None = field(repr=False, default=None)
    stored: bool = False
    db: str | None = None  # the records URL the session names (None: the default database)

    @property
    def verdict(self) -> str | None:
        """``PASS``, ``FAIL``, ``NO LIMITS`` (nothing to judge against: not a pass, exit 2) or None (no verdict
        reached). MARGINAL is a PASS here; the records and the report flag it."""
        v = (self.record or {}).get("verdict")
        if not v:
            return None
        return v.get("status") or ("PASS" if v.get("passed") else "FAIL")

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
    """``PROCEDURE-SERIAL-UTCSTAMP``, the session's folder name under ``$STATION_HOME/sessions``."""
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


def find_session(ref: str | Path) -> Path:
    """The journal of a session id (in ``$STATION_HOME/sessions``), folder or journal path."""
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
    """A new session on a connected robot: checks serial and limits, writes the journal header. ``db`` is only
    noted in the header (so that a resume stores where the run did); the engine does not open it."""
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
    header = ev.Header(
        session=sid, procedure=name, procedure_path=str(procedure.path.resolve()) if procedure else path,
        procedure_sha256=procedure.sha256 if procedure else sha256,
        procedure_title=procedure.title if procedure else title, mode="procedure" if procedure else "script",
        serial=str(serial), operator=operator or getpass.getuser(), station=socket.gethostname(),
        url=robot_url or getattr(robot, "url", "") or ident.url, model=robot.model.name, robot=_identity_dict(ident),
        limits={"path": lim.path, "version": lim.version, "sha256": lim.sha256},
        cell=None if the_cell is None else {"path": the_cell.path, "model": the_cell.model, "tool": the_cell.tool,
                                            "points": [p.to_dict() for p in the_cell.points.values()],
                                            **keep_out_to_doc(the_cell.keep_out)},
        options=opts, db=_db_for_journal(db), versions=_versions())
    journal = Journal.create(folder / "journal.jsonl", header)
    return Session(journal, robot, limits=table, limits_version=lim.version, cell=the_cell, options=opts,
                   progress=progress, touch=None if isinstance(touch, str) else touch, log=log)


def start(procedure: str | Path | Procedure, robot_url: str, serial: str, *, limits: str | Path | None = None,
          db: str | None = None, apply: bool = False, cell: str | Path | Cell | None = None,
          operator: str | None = None, options: dict | None = None, touch=None,
          progress: Callable[[int, int, str], None] | None = None, log: Callable[[str], None] | None = None,
          robot=None) -> Outcome:
    """Start a new session of ``procedure`` on the robot at ``robot_url`` and run it to the end (teardown
    included). Stores nothing: ``station.run`` does that with the outcome."""
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
    out = _execute(s, proc.checklist)
    out.db = db
    return out


def resume(session_ref: str | Path, *, touch=None, progress: Callable[[int, int, str], None] | None = None,
           log: Callable[[str], None] | None = None, robot=None) -> Outcome:
    """Continue an interrupted session: same procedure file (hash checked), same plan, recorded samples kept.
    The outcome's ``db`` is the records URL the journal names."""
    from station.robot import open_robot

    path = find_session(session_ref)
    try:
        header, events = read_journal(path)
    except JournalError as e:
        raise ConfigError(str(e)) from None
    if any(isinstance(e, ev.End) and e.status == "completed" for e in events):
        raise ConfigError(f"session {header.session} already completed; start a new one with station run")
    if not header.procedure_path:
        kind = header.procedure or "this kind of session"
        raise ConfigError(f"session {header.session} ({kind}) has no procedure file to resume; its samples "
                          f"are kept in {path} (use station solve on its samples.csv, or start a new session)")
    proc = load_procedure(header.procedure_path)
    if proc.sha256 != header.procedure_sha256:
        raise ProcedureError(f"procedure {proc.path} changed since session {header.session} started "
                             "(sha256 differs); resuming would mix two procedures")
    lim_info = header.limits or {}
    lim = load_limits(lim_info.get("path"))
    if lim.sha256 != lim_info.get("sha256"):
        raise ConfigError(f"limits file {lim.path} changed since session {header.session} started")
    robot = robot or open_robot(header.url)
    try:
        table = lim.for_procedure(robot.model.name, proc.name)
        journal = Journal.open(path)
    except BaseException:
        robot.close()
        raise
    s = Session(journal, robot, limits=table, limits_version=lim.version, cell=_cell_from_header(header.cell),
                options=dict(header.options), replay=events, progress=progress, touch=touch, log=log)
    s.event(ev.Resume(samples_kept=len(s.samples()), events_before=len(events)))
    out = _execute(s, proc.checklist)
    out.db = header.db
    return out


def _install_sigterm():
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise Terminated()

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:
        return None


def _execute(s: Session, body: Callable[[Session], None]) -> Outcome:
    status, err = "completed", None
    old = _install_sigterm()
    try:
        try:
            body(s)
        except KeyboardInterrupt as e:
            status, err = "interrupted", e
        except Exception as e:
            status, err = "error", e
        return finish(s, status, err)
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


def finish(s: Session, status: str, err: BaseException | None) -> Outcome:
    """Teardown (stop, compliance off) whatever happened, journal the fault and the end, close, write
    ``samples.csv``. Used by the runner and by scripted sessions; the caller stores and reports the outcome."""
    try:
        problems = s.safe_state()  # first: the robot stops, whatever the journal can still do
        if err is not None:
            s.event(ev.Fault(step=_failed_step(s), error=type(err).__name__, message=str(err) or type(err).__name__,
                             teardown=problems))
        elif problems:
            s.event(ev.Fault(step="teardown", error="teardown", message="; ".join(problems)))
        s.event(ev.End(status=status, passed=_passed(s.verdict),
                       n_samples=len(s.samples())))
    finally:
        with contextlib.suppress(Exception):  # closing a dead connection must not hide the original outcome
            s.robot.close()
        s.journal.close()
    record = s.record_dict()
    write_samples_csv(s.folder / "samples.csv", s.samples(), joint_units(s.model),
                      comment=f"session {s.id}, model {s.model.name}")
    return Outcome(s.id, s.folder, status, _passed(s.verdict), record,
                   error=err, db=s.journal.header.db)


def _passed(verdict: dict | None) -> bool | None:
    """None without a verdict and for NO LIMITS (passed None): neither a pass nor a fail."""
    return None if verdict is None or verdict.get("passed") is None else bool(verdict["passed"])


def _failed_step(s: Session) -> str | None:
    for e in reversed(s.events("step")):
        if e.status in ("start", "failed"):
            return e.name
    return None
