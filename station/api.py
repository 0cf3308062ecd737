"""The scripted Python API: what the shipped procedures use, for your own scripts (docs/scripting.md).

    import station

    robot = station.connect("ur://127.0.0.2?model=ur5e")
    with station.session(robot, serial="20235500001", cell="cell.yaml") as s:
        plan = s.plan(s.points("socket"), identify="offsets")
        for pose in s.todo(plan):
            s.approach(pose); s.seat(pose); s.record(pose); s.leave(pose)
        result = s.solve(identify="offsets")
    print(s.outcome.report)

Everything a session does is journaled (``$STATION_HOME/sessions/<id>/journal.jsonl``); leaving the ``with``
block stops the robot, whatever happened, and stores the record."""

from __future__ import annotations

import contextlib
import hashlib
import inspect
from collections.abc import Iterator
from pathlib import Path

from station.engine import Outcome, Session, load_procedure
from station.engine import resume as _resume
from station.engine import start as _start
from station.engine.runner import create_session, finish
from station.publish import check_records, publish


def connect(url: str, **kwargs):
    """A connected robot (``station.robot.Robot``) for a URL: ``ur://``, ``canopen+virtual://``,
    ``canopen+socketcand://``, ``dynamixel://``."""
    from station.robot import open_robot

    return open_robot(url, **kwargs)


@contextlib.contextmanager
def session(robot, serial: str, *, name: str | None = None, cell=None, limits=None, db: str | None = None,
            apply: bool = False, options: dict | None = None, touch=None, operator: str | None = None,
            store: bool = True, report: bool = True, progress=None) -> Iterator[Session]:
    """A journaled session on ``robot`` (a ``Robot`` or a URL). Connects/identifies and checks the state on
    entry; on exit (also on an exception or Ctrl-C) stops the robot, journals the end, stores the record
    (``store``) and writes the report (``report``). The outcome is ``s.outcome`` afterwards."""
    if store:
        check_records(db)
    if isinstance(robot, str):
        robot = connect(robot)
    caller = Path(inspect.stack()[2].filename)
    sha = hashlib.sha256(caller.read_bytes()).hexdigest() if caller.is_file() else None
    name = name or (caller.stem if caller.is_file() else "script")
    try:
        s = create_session(robot, serial, name=name, sha256=sha, path=str(caller), limits=limits, db=db, apply=apply,
                           cell=cell, operator=operator, options=options, touch=touch, progress=progress)
    except BaseException:
        robot.close()
        raise
    status, err = "completed", None
    try:
        s.connect()
        s.check_state()
        yield s
    except KeyboardInterrupt as e:
        status, err = "interrupted", e
    except Exception as e:
        status, err = "error", e
    finally:
        s.outcome = publish(finish(s, status, err), db=db, store=store, report=report, log=s.log)
    if err is not None:
        raise err


def run(procedure: str | Path, robot_url: str, serial: str, *, db: str | None = None, report: bool = True,
        store: bool = True, **kwargs) -> Outcome:
    """Run a shipped procedure (by name) or a procedure file, like ``station run``: the record is stored in the
    records database (``db``) and the report written before it returns. Returns the outcome (``status``,
    ``passed``, ``record``, ``report``, ``stored``, ``store_error``, ``verdict``, ``exit_code``). With ``store``
    the database is checked before the robot is opened (a bad URL or a read-only database: nothing moves)."""
    if store:
        check_records(db)
    out = _start(procedure, robot_url, serial, db=db, **kwargs)
    return publish(out, db=db, store=store, report=report, log=kwargs.get("log"))


def resume(session_id: str | Path, *, db: str | None = None, report: bool = True, store: bool = True,
           **kwargs) -> Outcome:
    """Continue an interrupted session, like ``station resume`` (stored where the session names, or ``db``;
    checked before the robot is opened)."""
    if store:
        check_records(db if db is not None else _session_db(session_id))
    out = _resume(session_id, **kwargs)
    return publish(out, db=db, store=store, report=report, log=kwargs.get("log"))


def _session_db(session_id) -> str | None:
    from station.engine.journal import JournalError, read_journal
    from station.engine.runner import find_session
    from station.robot.errors import ConfigError

    try:
        return read_journal(find_session(session_id))[0].db
    except JournalError as e:
        raise ConfigError(str(e)) from None


def solve(model, obs, **kwargs):
    """``station.solver.solve`` (see docs/solver.md)."""
    from station.solver import solve as _solve

    return _solve(model, obs, **kwargs)


__all__ = ["Outcome", "Session", "connect", "load_procedure", "resume", "run", "session", "solve"]
