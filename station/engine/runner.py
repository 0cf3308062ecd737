"""Run a procedure on a robot with guaranteed teardown; the outcome carries the session record.

Whatever happens inside the checklist (a fault, a bus error, Ctrl-C, SIGTERM), the robot is stopped and left
non-compliant, the fault and the end are journaled and ``samples.csv`` is written, so a resume can continue.
The engine stores nothing in the records database and writes no report: the caller hands the outcome on
(``station.publish.publish``, used by ``station.run``/``station resume``/the CLI), and shows a verdict only
once the record is stored."""

from __future__ import annotations

import contextlib
import functools
import getpass
import hashlib
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
from station.engine.cell import Cell, load_cell
from station.engine.declare import session_options
from station.engine.journal import Journal, JournalError, JournalWriteError, check_space, check_writable, read_journal
from station.engine.limits import check_limits, load_limits
from station.engine.procedure import Procedure, is_name, load_procedure, procedure_for_resume, shipped_names
from station.engine.session import Session
from station.kinematics.collision import keep_out_to_doc
from station.robot.errors import ConfigError, DeviceFault, StationError
from station.robot.protocol import adopt_serial


class DiskError(StationError):
    """The journal's folder cannot take the session (read-only, not enough free space): one line, exit 2."""


def _disk_ok(folder: Path, what: str) -> None:
    try:
        check_writable(folder)
        check_space(folder, what)
    except JournalWriteError as e:
        raise DiskError(str(e)) from None


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C (teardown, journal, exit)."""


class Aborted(KeyboardInterrupt):
    """ABORT from the operator panel or the line (OPC UA ``Abort()``): handled like Ctrl-C (teardown, journal,
    the session ends interrupted and stays resumable)."""


class RunControl:
    """A run seen from other threads (the operator panel, the OPC UA server): ``abort()`` and the live
    ``session`` once it exists.

    Every motion of the run (the checklist's, the touch providers', the write-back's check touch) goes through
    the robot's ``move_joints``/``move_linear``; :meth:`attach` guards those two on the run's robot object, so an
    abort during a move stops the robot at once through the driver's stop path (which ends the waited move
    from another thread: tests/e2e/test_bus_conformance.py), and no move starts after an abort."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.reason: str | None = None
        self.session: Session | None = None
        self._robot = None
        self._moving = 0
        self.stopped_moving: str | None = None  # what was moving when the abort stopped it

    @property
    def aborted(self) -> bool:
        return self.reason is not None

    def abort(self, reason: str = "aborted by the operator") -> None:
        with self._lock:
            if self.reason is None:
                self.reason = reason
            robot = self._robot if self._moving else None
        if robot is not None:
            with contextlib.suppress(Exception):  # the teardown stops it again and journals what failed
                robot.stop()

    def check(self) -> None:
        """Raise :class:`Aborted` once an abort was asked for."""
        if self.reason is not None:
            raise Aborted(self.reason)

    def attach(self, s: Session) -> None:
        self.session = s
        self._robot = s.robot
        for name in ("move_joints", "move_linear"):
            fn = getattr(s.robot, name, None)
            if callable(fn):
                setattr(s.robot, name, self._guard(fn, s))

    def _guard(self, move, s: Session):
        @functools.wraps(move)
        def guarded(*args, **kwargs):
            with self._lock:
                self.check()
                self._moving += 1
            try:
                return move(*args, **kwargs)
            except Exception:
                if self.reason is None:
                    raise
                step = s.steps.current
                what = step.describe() if step is not None and step.pose is not None else "a move"
                self.stopped_moving = what
                raise Aborted(f"{self.reason}; the robot was stopped during {what}") from None
            finally:
                with self._lock:
                    self._moving -= 1

        return guarded


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
    store_error: str | None = None  # why the record is NOT STORED (``station records sync`` stores it later)
    model: object = field(repr=False, default=None)  # the kinematic model the session solved with (read-only)

    @property
    def verdict(self) -> str:
        """What the terminal shows last: PASS, FAIL, NO LIMITS (nothing to judge against: not a pass, exit 2),
        NOT STORED, ERROR or INTERRUPTED. MARGINAL is a PASS here; the records and the report flag it."""
        if self.store_error is not None:
            return "NOT STORED"
        if self.status == "interrupted":
            return "INTERRUPTED"
        if self.status != "completed":
            return "ERROR"
        if ((self.record or {}).get("verdict") or {}).get("status") == "NO LIMITS":
            return "NO LIMITS"
        if self.passed is None:
            return "ERROR"
        return "PASS" if self.passed else "FAIL"

    @property
    def exit_code(self) -> int:
        if self.status == "interrupted":
            return 130
        if self.store_error is not None or self.status != "completed" or self.passed is None:
            return 2
        return 0 if self.passed else 1


def station_home() -> Path:
    return Path(os.environ.get("STATION_HOME") or "./station-data")


def new_session_id(procedure: str, serial: str) -> str:
    """``PROCEDURE-SERIAL-UTCSTAMP``, the session's folder name under ``$STATION_HOME/sessions``."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in serial) or "unknown"
    return f"{procedure}-{safe}-{stamp}"


def versions() -> dict:
    """The versions a journal header names: python, the station, numpy, scipy."""
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


def _cell_from_header(d: dict | None, where: str = "journal") -> Cell | None:
    """The session's cell as journaled (SI), checked as a cell file is (types, finite, within bounds): one line
    naming the journal and the field. Pictures are not taken from a journal (the panel shows its own cell's)."""
    if not d:
        return None
    import dataclasses

    from station.engine.cell import CellError, cell_from_dict
    from station.textfile import YamlDoc

    points = d.get("points")
    if isinstance(points, list):
        points = [{k: v for k, v in p.items() if k != "image"} if isinstance(p, dict) else p for p in points]
    doc = {"format": "station-cell/1", "units": {"length": "m", "angle": "rad"}, "points": points,
           **{k: d[k] for k in ("model", "tool", "mounting", "keep_out", "planes") if d.get(k) is not None}}
    # the known distances as the solve was told them ([a, b, metres, std metres or None]; a journal of an older
    # station has none): a resumed session solves the same problem
    dist = d.get("distances")
    if isinstance(dist, list) and dist:
        doc["distances"] = [{"between": [x[0], x[1]], "distance": x[2], **({} if x[3] is None else {"std": x[3]})}
                            if isinstance(x, list) and len(x) == 4 else x for x in dist]
    unknown = set(d) - {"path", "model", "tool", "points", "mounting", "keep_out", "distances", "planes"}
    try:
        if unknown:
            raise CellError(f"{where}: field cell.{sorted(unknown)[0]}: unknown field of a journaled cell")
        cell = cell_from_dict(YamlDoc(f"{where}: field cell", doc), f"{where}: field cell")
    except CellError as e:
        raise ConfigError(" ".join(str(e).split())) from None
    return dataclasses.replace(cell, path=str(d.get("path") or "journal"))


def _check_options(options: dict, where: str, procedure: Procedure) -> None:
    """The journaled options a resume acts on, held to their declarations (``declare.session_options``: the
    engine's, the plan's and the procedure's own; a journal is data: it may be damaged)."""
    declared = session_options(procedure.module.checklist)
    for name, value in options.items():
        o = declared.get(name)
        if o is not None and not o.holds(value):
            raise ConfigError(f"{where}: field options.{name}: {str(value)[:60]!r} is not {o.kind.stored_form}")


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
                   log: Callable[[str], None] | None = None, robot_url: str = "", prompt=None,
                   control: RunControl | None = None) -> Session:
    """A new session on a connected robot: checks serial and limits, writes the journal header. ``db`` is only
    noted in the header (so that a resume stores where the run did); the engine does not open it."""
    from station.engine.session import _identity_dict

    name = procedure.name if procedure else (name or "script")
    check_journal_folder()  # read-only or full: one line before anything is journaled or moved
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
        procedure_version=procedure.version if procedure else None,
        procedure_title=procedure.title if procedure else title, mode="procedure" if procedure else "script",
        serial=str(serial), operator=operator or operator_name(), station=socket.gethostname(),
        url=robot_url or getattr(robot, "url", "") or ident.url, model=robot.model.name, robot=_identity_dict(ident),
        limits={"path": lim.path, "version": lim.version, "sha256": lim.sha256},
        cell=None if the_cell is None else {"path": the_cell.path, "model": the_cell.model, "tool": the_cell.tool,
                                            "points": [p.to_dict() for p in the_cell.points.values()],
                                            "distances": [list(d) for d in the_cell.distances],
                                            "planes": list(the_cell.planes),
                                            **keep_out_to_doc(the_cell.keep_out)},
        options=opts, db=_db_for_journal(db), versions=versions())
    journal = Journal.create(folder / "journal.jsonl", header)
    s = Session(journal, robot, limits=table, limits_version=lim.version, cell=the_cell, options=opts,
                progress=progress, touch=None if isinstance(touch, str) else touch, log=log, prompt=prompt)
    if control is not None:
        control.attach(s)
    s.given = set(options or {})  # what the caller chose (checked against the procedure), not its DEFAULTS
    s.declared = _declared(procedure)
    return s


def technician_session(robot, header: ev.Header | dict, *, folder: str | Path | None = None,
                       session_id: str | None = None, model=None) -> Session:
    """A technician's session (``station jog``): the journal (header ``mode: technician``, procedure ``jog``;
    ``folder`` default ``$STATION_HOME/sessions/<id>``) and the engine session that journals what the
    technician records. The UI drives the robot itself; ``samples.csv`` follows every record and discard.
    A folder that already holds a journal is refused (a session is never appended to by a second run)."""
    from station.engine.journal import make_header

    head = make_header(header)
    head.mode = "technician"
    head.session = session_id or new_session_id(head.procedure or "jog", str(head.serial or "unknown"))
    folder = Path(folder) if folder is not None else station_home() / "sessions" / head.session
    if (folder / "journal.jsonl").exists():
        raise ConfigError(f"session folder {folder} already has a journal; choose a new --session folder")
    folder.mkdir(parents=True, exist_ok=True)
    s = Session(Journal.create(folder / "journal.jsonl", head), robot, options=dict(head.options), model=model)
    s.write_samples_csv()
    return s


def _declared(procedure: Procedure | None) -> dict | None:
    """The measurements a procedure declares, by name (None: it declares none, a script: not checked)."""
    measurements = procedure.measurements if procedure is not None else None
    return None if measurements is None else {m.name: m for m in measurements}


def operator_name() -> str:
    """Who runs the station: the login name (``unknown`` where there is none, as in some containers)."""
    try:
        return getpass.getuser()
    except Exception:  # getpass raises OSError/KeyError without a login name
        return "unknown"


def start(procedure: str | Path | Procedure, robot_url: str, serial: str, *, limits: str | Path | None = None,
          db: str | None = None, apply: bool = False, cell: str | Path | Cell | None = None,
          operator: str | None = None, options: dict | None = None, touch=None,
          progress: Callable[[int, int, str], None] | None = None, log: Callable[[str], None] | None = None,
          robot=None, prompt=None, control: RunControl | None = None) -> Outcome:
    """Start a new session of ``procedure`` on the robot at ``robot_url`` and run it to the end (teardown
    included). Stores nothing: ``station.run`` does that with the outcome. ``prompt(question) -> answer`` is the
    operator's side of ``s.ask`` (default: the terminal); ``control`` lets another thread abort the run."""
    from station.robot import open_robot

    proc = procedure if isinstance(procedure, Procedure) else load_procedure(procedure)
    if (options or {}).get("identify") and proc.identify is None:
        raise ConfigError(f"--identify: procedure {proc.name} solves nothing (it has no IDENTIFY group); it "
                          "applies to procedures that solve: " + ", ".join(solving_procedures()))
    lim = load_limits(limits)  # a bad limits or cell file fails before the robot is opened
    if proc.measurements is not None:  # what the procedure declares against every section of the file for it
        check_limits(proc.name, proc.measurements, lim)
    if cell is not None:
        load_cell(cell)
    check_journal_folder()
    robot = robot or open_robot(robot_url)
    try:
        s = create_session(robot, serial, procedure=proc, limits=limits, db=db, apply=apply, cell=cell,
                           operator=operator, options=options, touch=touch, progress=progress, log=log,
                           robot_url=robot_url, prompt=prompt, control=control)
    except JournalWriteError as e:
        robot.close()
        raise DiskError(str(e)) from None
    except BaseException:
        robot.close()
        raise
    out = _execute(s, proc.checklist, control)
    out.db = db
    return out


def resume(session_ref: str | Path, *, touch=None, progress: Callable[[int, int, str], None] | None = None,
           log: Callable[[str], None] | None = None, robot=None, prompt=None,
           control: RunControl | None = None, instruments: dict[str, str] | None = None,
           payload: dict | None = None, procedure: str | Path | None = None) -> Outcome:
    """Continue an interrupted session: the same procedure, same plan, recorded samples kept. The procedure is
    found again by the journaled name in the shipped package and the configured folders
    (``station.engine.procedure.procedure_for_resume``), or is the ``procedure`` file the caller's own command
    line names; it runs only if its SHA-256 is the journaled one (checked before it is compiled): a journal
    never names the code that runs. The outcome's ``db`` is the records URL the journal names. ``instruments``
    (``{"tracker": URL}``) gives an instrument option of the session a new address (the instrument came back on
    another port): journaled as an ``instrument_url`` event and used by every later resume too; the procedure
    checks the instrument there is the one the session started with. ``payload`` (``{"mass": kg, "com": [x, y, z]
    m}``) is only checked: the session's journaled payload is used, and a resume given another one is refused
    before the robot opens."""
    from station.robot import open_robot

    path = find_session(session_ref)
    try:
        header, events = read_journal(path)
    except JournalError as e:
        raise ConfigError(str(e)) from None
    if any(isinstance(e, ev.End) and e.status == "completed" for e in events):
        raise ConfigError(f"session {header.session} already completed; start a new one with station run")
    if any(isinstance(e, ev.Writeback) and e.kind == "restore" and e.phase == "written" for e in events):
        raise ConfigError(f"session {header.session}: its write-back was rolled back with station restore; "
                          "start a new session with station run")
    if not header.procedure_path or header.mode != "procedure":
        kind = header.procedure or "this kind of session"
        what = "is a script's session (run the script again)" if header.mode == "script" else \
            "has no procedure file to resume"
        raise ConfigError(f"session {header.session} ({kind}) {what}; its samples are kept in {path} (use station "
                          "solve on its samples.csv, or start a new session)")
    _check_header(path, header)
    cell = _cell_from_header(header.cell, f"journal {path}:1")
    # found by NAME where the station's configuration says procedures live, and hashed BEFORE it is compiled:
    # the path the journal names is never read, so a damaged or planted journal cannot run code
    proc = procedure_for_resume(header.procedure, header.procedure_sha256, file=procedure,
                                where=f"session {header.session}")
    _check_options(header.options, f"journal {path}:1", proc)
    lim_info = header.limits or {}
    if lim_info.get("path") is not None:  # hashed before it is parsed: a journal may name any file
        from station.textfile import read_capped

        data = read_capped(lim_info["path"], ConfigError, f"limits file {lim_info['path']}")
        if hashlib.sha256(data).hexdigest() != lim_info.get("sha256"):
            raise ConfigError(f"limits file {lim_info['path']} changed since session {header.session} started "
                              "(sha256 differs)")
    lim = load_limits(lim_info.get("path"))
    if lim.sha256 != lim_info.get("sha256"):
        raise ConfigError(f"limits file {lim.path} changed since session {header.session} started")
    options, moved = _instrument_urls(header, events, instruments)  # a bad --tracker: before the robot opens
    if payload is not None:
        _same_payload(header, payload)
    _disk_ok(path.parent, "not resuming")
    robot = robot or open_robot(header.url)
    try:
        table = lim.for_procedure(robot.model.name, proc.name)
        journal = Journal.open(path)
    except BaseException:
        robot.close()
        raise
    s = Session(journal, robot, limits=table, limits_version=lim.version, cell=cell,
                options=options, replay=events, progress=progress, touch=touch, log=log, prompt=prompt)
    s.declared = _declared(proc)
    if control is not None:
        control.attach(s)
    try:
        if journal.torn:  # reported, never silently dropped: on the terminal and in the journal
            s.log(f"station: warning: {journal.torn}")
            s.event(ev.Warn(step="resume", message=journal.torn))
        s.event(ev.Resume(samples_kept=len(s.samples()), events_before=len(events)))
        for name, (old, new) in moved.items():
            s.event({"type": "instrument_url", "option": name, "old": old, "new": new})
    except BaseException:
        robot.close()
        journal.close()
        raise
    out = _execute(s, proc.checklist, control)
    out.db = header.db
    return out


def _instrument_urls(header: ev.Header, events: list, given: dict[str, str] | None) -> tuple[dict, dict]:
    """The session's options for a resume: the header's, with every journaled ``instrument_url`` replacement
    applied in order, then the ``given`` ones (``{option: URL}``); and which of the given ones change a URL
    (``{option: (old, new)}``, to journal). Only an instrument URL option the session has can be replaced."""
    def is_url(v) -> bool:
        return isinstance(v, str) and "://" in v

    opts = dict(header.options)
    for e in events:  # only a URL option replaced by a URL: a damaged journal cannot turn on e.g. "apply"
        d = getattr(e, "data", None)
        if getattr(e, "type", None) == "instrument_url" and isinstance(d, dict) and is_url(d.get("new")) \
                and is_url(opts.get(str(d.get("option")))):
            opts[str(d["option"])] = d["new"]
    moved = {}
    for name, url in (given or {}).items():
        if not is_url(opts.get(name)):
            raise ConfigError(f"--{name} {url}: session {header.session} used no --{name}; nothing to redirect")
        if not is_url(url):
            raise ConfigError(f"--{name} {url!r}: expected an instrument URL like tcp://HOST:PORT")
        if url != opts[name]:
            moved[name] = (opts[name], url)
            opts[name] = url
    return opts, moved


def _same_payload(header: ev.Header, given: dict) -> None:
    """A resume given ``--payload``: the session's journaled payload must be that one (same mass and centre of
    mass to 1 g / 0.1 mm): the model's compliance terms and every sample so far belong to it."""
    from station.kinematics.gravity import same_payload, show_payload

    had = header.options.get("payload")
    if not isinstance(had, dict):
        raise ConfigError(f"--payload {show_payload(given)}: session {header.session} was run without a payload; "
                          "resume it without --payload, or start a new session")
    if not same_payload(had, given):
        was = show_payload(had) if {"mass", "com"} <= set(had) else repr(had)
        raise ConfigError(f"--payload {show_payload(given)}: session {header.session} was run with {was}; the "
                          "samples so far were measured under that load: resume with it (or without --payload), or "
                          "start a new session")


def check_journal_folder() -> Path:
    """``$STATION_HOME/sessions`` can take a journal (writable, enough free space): checked before the robot is
    opened, so a read-only or full disk is one line and nothing moves."""
    folder = station_home() / "sessions"
    _disk_ok(folder, "not starting the session")
    return folder


def restore(session_ref: str | Path, *, robot=None, log: Callable[[str], None] | None = None) -> dict:
    """``station restore SESSION``: write the session's ``calibration-backup.json`` (the device calibration
    before its first write-back) back into the robot, as a transaction journaled in the session
    (``writeback`` events with ``kind: restore``). Checked before the robot is opened: the backup, the journal
    folder; after: the robot's serial. Returns ``{"before", "after", "readback", "session"}`` (SI)."""
    from station.engine.writeback import BACKUP, load_backup, read_device
    from station.engine.writeback import restore as _restore
    from station.robot import open_robot

    path = find_session(session_ref)
    try:
        header, events = read_journal(path)
    except JournalError as e:
        raise ConfigError(str(e)) from None
    load_backup(path.parent)  # one line when missing or damaged, before the robot is opened
    _disk_ok(path.parent, "not restoring")
    robot = robot or open_robot(header.url)
    try:
        adopt_serial(robot.identity(), header.serial)  # the backup belongs to this robot only
        journal = Journal.open(path)
    except BaseException:
        robot.close()
        raise
    s = Session(journal, robot, options=dict(header.options), replay=events, log=log)
    old = _install_sigterm()
    try:
        before = read_device(robot)
        with s.step("restore", backup=str(path.parent / BACKUP)):
            readback = _restore(robot, path.parent, s.id, event=s.event, tolerance=s.readback_tolerance,
                                note=f"station restore: {BACKUP} written back")
    except Exception as e:
        with contextlib.suppress(JournalWriteError):
            s.event(ev.Fault(step="restore", error=type(e).__name__, message=str(e) or type(e).__name__,
                             teardown=s.safe_state()))
        raise
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
        with contextlib.suppress(Exception):
            robot.close()
        journal.close()
    return {"session": s.id, "before": before, "after": load_backup(path.parent)["before"], "readback": readback,
            "record": s.record_dict(), "db": header.db}


def _check_header(path: Path, header: ev.Header) -> None:
    """The header fields resume acts on, beyond their types (the schema checked those): one line naming the
    journal and the field."""
    where = f"journal {path}:1"
    if not is_name(header.procedure):
        raise ConfigError(f"{where}: field procedure: {header.procedure[:80]!r} is not a procedure name")
    sha = header.procedure_sha256 or ""
    if len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha):
        raise ConfigError(f"{where}: field procedure_sha256: {sha!r} is not a sha256 hex digest")
    if not str(header.procedure_path).endswith(".py"):
        raise ConfigError(f"{where}: field procedure_path: {header.procedure_path!r} is not a procedure .py file")
    if not header.url or "://" not in header.url:
        raise ConfigError(f"{where}: field url: {header.url!r} is not a robot URL")
    if not str(header.serial).strip():
        raise ConfigError(f"{where}: field serial: empty")
    lim = header.limits
    if not isinstance(lim, dict) or not isinstance(lim.get("sha256"), str):
        raise ConfigError(f"{where}: field limits: needs path, version and sha256 of the limits file")


def _install_sigterm():
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise Terminated()

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:
        return None


def solving_procedures() -> list[str]:
    """The shipped procedures that solve for a parameter group (those ``--identify`` applies to)."""
    out = []
    for name in shipped_names():
        with contextlib.suppress(ConfigError):
            if load_procedure(name).identify:
                out.append(name)
    return out


def _execute(s: Session, body: Callable[[Session], None], control: RunControl | None = None) -> Outcome:
    status, err = "completed", None
    old = _install_sigterm()
    try:
        try:
            body(s)
            if control is not None:  # an abort after the last move still ends the run ABORTED, never PASS
                control.check()
        except KeyboardInterrupt as e:
            status, err = "interrupted", e
        except Exception as e:
            status, err = "error", e
        return finish(s, status, err)
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


def finish(s: Session, status: str, err: BaseException | None) -> Outcome:
    """Teardown (stop, compliance off) whatever happened, journal the fault and the end, close the session's
    measuring instruments and the robot, write ``samples.csv``. Used by the runner and by scripted sessions;
    the caller stores and reports the outcome.
    An incomplete end is never PASS: a teardown that could not bring the robot to its safe state after a
    completed checklist, or a journal that lost an event, turns the outcome into an error (exit 2) whose one-line
    reason says so (docs/reliability.md)."""
    try:
        problems = s.safe_state()  # first: the robot stops, whatever the journal can still do
        released = s.close_instruments()  # the session's measuring instruments: plugs the teardown releases
        if released:  # an instrument is no safety matter: said, not turned into a fault
            with contextlib.suppress(JournalWriteError):
                s.event(ev.Warn(step="teardown", message="; ".join(released)))
        if err is None and problems:
            # a fault after the last sample (during solve/export, or the teardown itself): never PASS
            status, err = "error", DeviceFault("teardown could not leave the robot safe: " + "; ".join(problems))
        if err is None and s.journal.lost:
            status, err = "error", JournalWriteError(f"journal {s.journal.path}: {len(s.journal.lost)} event(s) "
                                                     "could not be written; the session cannot PASS")
        if err is not None:
            step, pose = _failed_step(s, err)
            with contextlib.suppress(JournalWriteError):
                s.event(ev.Fault(step=step, error=type(err).__name__, message=str(err) or type(err).__name__,
                                 teardown=problems, pose=pose))
        with contextlib.suppress(JournalWriteError):  # without an End the session stays resumable
            s.end(status, _passed(s.verdict) if status == "completed" else None)
        if s.journal.lost and status == "completed":
            status, err = "error", JournalWriteError(f"journal {s.journal.path}: the end of the session could "
                                                     "not be written; the session cannot PASS")
    finally:
        s.close_instruments()  # again: a teardown interrupted above must not leave an instrument open
        with contextlib.suppress(Exception):  # closing a dead connection must not hide the original outcome
            s.robot.close()
        s.journal.close()
    record = s.record_dict()
    try:
        s.write_samples_csv()
    except OSError as e:  # the journal holds every sample; samples.csv is a convenience copy
        s.log(f"samples.csv not written: {e.strerror or e}")
    write_result_json(s.folder, record.get("result"), s.log)
    return Outcome(s.id, s.folder, status, _passed(s.verdict) if status == "completed" else None, record,
                   error=err, db=s.journal.header.db, model=s.model)


def write_result_json(folder: Path, result: dict | None, log: Callable[[str], None]) -> None:
    """``result.json``: the session's solve result in the format of ``station solve --out``
    (``station-calibration/1``), what ``station fk --calibration``, ``station model export --calibration`` and
    ``station run correction_map --calibration`` read. Written atomically after every run that solved; a copy
    of the journal's last result event, so a failure to write it is a note, never a lost session."""
    if not result:
        return
    from station.safeio import dumps_json, write_atomic

    try:
        write_atomic(folder / "result.json", dumps_json(result) + "\n")
    except OSError as e:
        log(f"result.json not written: {e.strerror or e}")


def _failed_step(s: Session, err: BaseException) -> tuple[str | None, int | None]:
    """The step a fault came in, and its pose: the innermost step ``err`` came out of (approach of pose N, solve);
    else the step still running (a teardown fault); else "after STEP" (between steps of the checklist, e.g. in
    the checklist's own code)."""
    step = s.steps.failed_for(err) or s.steps.current
    if step is not None:
        return step.name, step.pose
    last = s.steps.last
    if last is not None:
        return f"after {last.name}", last.pose
    return None, None


def _passed(verdict: dict | None) -> bool | None:
    """None without a verdict and for NO LIMITS (passed None): neither a pass nor a fail."""
    return None if verdict is None or verdict.get("passed") is None else bool(verdict["passed"])
