"""One station, one unit at a time: the state machine behind the operator panel and the OPC UA server.

It runs the same engine as ``station run`` (``station.api.run`` / ``station.api.resume``, with a progress
callback) in a worker thread, asks the operator through prompts, and reports a verdict only once the session
record has been read back from the records database (never PASS unless stored: a record that did not store
ends as ``NOT STORED``; the journal keeps everything and can be stored later)."""

from __future__ import annotations

import contextlib
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from station.engine.procedure import BadAnswer, Question
from station.engine.runner import Aborted, RunControl
from station.panel.reasons import Reason, explain, plain_failure, refused, where

STATES = ("idle", "running", "prompt", "done")
NO_RESULT = "no unit has finished since the station started"


class PanelError(ValueError):
    """A request the station refuses (wrong state, bad input); the API answers 409/400 with its text."""


class WrongState(PanelError):
    """A request the station's present state refuses (a unit running, nothing running, no question open): 409."""


class BadProcedure(PanelError):
    """A start request naming a procedure the station does not run (a path, an unknown name): 400."""


class PromptRefused(PanelError):
    """An answer the open question refuses (400, one line); the question stays open."""


@dataclass
class PanelConfig:
    robot: str
    cell: str | None = None
    procedure: str = "zero_offsets"
    limits: str | None = None
    db: str | None = None
    options: dict = field(default_factory=dict)
    touch: str | None = None  # "manual": the operator touches each point (a prompt per pose)
    confirm: bool = True  # ask the operator to confirm the unit is clamped before anything moves


_STEPS = {"starting": "Starting", "resuming": "Resuming", "connecting": "Connecting to the robot",
          "all poses recorded": "Calculating the calibration", "aborting": "Stopping the robot"}


def activity(state: str, step: str | None) -> str | None:
    """What the station is doing, in the operator's words (the engine's ``step`` is for the journal):
    ``pose 3/14 (A, fit)`` -> ``Measuring point A (pose 3 of 14)``."""
    if state == "prompt":
        return "Waiting for you"
    if state not in ("running",) or not step:
        return None
    m = re.fullmatch(r"pose (\d+)/(\d+) \((.*), (\w+)\)", step)
    if m:
        what = "Checking" if m.group(4) == "holdout" else "Measuring"
        return f"{what} point {m.group(3)} (pose {m.group(1)} of {m.group(2)})"
    return _STEPS.get(step, step[:1].upper() + step[1:])


class Controller:
    """Thread-safe state; ``snapshot()`` is what ``GET /api/state`` returns."""

    def __init__(self, config: PanelConfig) -> None:
        self.config = config
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self.version = 0
        self._abort = threading.Event()
        self._answer: str | None = None
        self._answered = threading.Event()
        self._question: Question | None = None
        self._thread: threading.Thread | None = None
        self._control: RunControl | None = None
        self._cell = None
        self._s = self._blank()
        self._last = self._result_doc(verdict="", reason=NO_RESULT)

    # ---- state ---------------------------------------------------------------------------------------
    @staticmethod
    def _blank() -> dict:
        return {"state": "idle", "serial": None, "operator": None, "procedure": None, "step": None,
                "samples": 0, "samples_planned": 0, "verdict": None, "session": None, "failing": [],
                "message": None, "prompt": None, "report": None, "stored": None,
                "started": None, "finished": None, "residuals": [], "residuals_model": None,
                "reason": None, "action": None, "detail": None, "where": None, "resumable": False,
                "cause": None}

    def _set(self, **kw) -> None:
        with self._lock:
            self._s.update(kw)
            self.version += 1
            self._changed.notify_all()

    def snapshot(self) -> dict:
        with self._lock:
            out = dict(self._s)
            out["progress"] = (out["samples"] / out["samples_planned"]) if out["samples_planned"] else 0.0
            out["activity"] = activity(out["state"], out["step"])
            out["version"] = self.version
            return out

    def last_result(self) -> dict:
        """The last finished (or refused) unit for the line (OPC UA ``LastResult``): always a document with the
        verdict and the reason in words; before the first unit ``verdict`` is ``""``. A new start keeps it
        until the new unit ends."""
        with self._lock:
            return self._last

    def _result_doc(self, **kw) -> dict:
        doc = {"session": None, "serial": None, "procedure": None, "operator": None, "verdict": None,
               "reason": None, "action": None, "detail": None, "where": None, "cause": None, "resumable": False,
               "stored": None,
               "failing": [], "report": None, "finished": None, "measurements": [], "parameters": {}}
        doc.update(kw)
        return doc

    def _end(self, *, measurements: list | None = None, parameters: dict | None = None, **kw) -> None:
        """The unit ended (or was refused): the verdict screen and the line's ``LastResult``, in one change."""
        with self._lock:
            self._s.update(state="done", finished=time.time(), **kw)
            s = self._s
            self._last = self._result_doc(
                **{k: s[k] for k in ("session", "serial", "procedure", "operator", "verdict", "reason", "action",
                                     "detail", "where", "cause", "resumable", "stored", "failing", "report")},
                finished=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(s["finished"])),
                measurements=measurements or [], parameters=parameters or {})
            self.version += 1
            self._changed.notify_all()

    def _ended_by(self, reason, verdict: str, message: str | None = None, **kw) -> None:
        """End with ``verdict`` for ``reason`` (a :class:`~station.panel.reasons.Reason`)."""
        with self._lock:
            where_ = where(self._s["samples"], self._s["samples_planned"]) if verdict in ("ERROR", "ABORTED") \
                else None
        self._end(verdict=verdict, reason=reason.text, action=reason.action, detail=reason.detail,
                  cause=reason.kind, where=where_, message=message if message is not None else reason.detail,
                  step="stopped", **kw)

    def wait_change(self, version: int, timeout: float) -> int:
        with self._lock:
            self._changed.wait_for(lambda: self.version != version, timeout=timeout)
            return self.version

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ---- commands ----------------------------------------------------------------------------------
    def clear(self) -> None:
        """The next serial was scanned: the verdict screen goes away."""
        with self._lock:
            if self.busy:
                raise WrongState("a unit is running; abort it first")
            self._s = self._blank()
            self.version += 1
            self._changed.notify_all()

    def start(self, serial: str, operator: str, procedure: str | None = None, *, confirm: bool | None = None,
              wait_session: float = 0.0) -> str | None:
        """Start a unit. Returns the session id once the journal exists (waits up to ``wait_session`` s)."""
        serial, operator = (serial or "").strip(), (operator or "").strip()
        if not serial:
            raise PanelError("serial is required (scan the unit's label)")
        if not operator:
            raise PanelError("operator is required (sign in first)")
        if any(c.isspace() for c in serial) or len(serial) > 64:
            raise PanelError(f"serial {serial!r} is not a serial number (no spaces, at most 64 characters)")
        proc = self._requested_procedure(procedure)
        with self._lock:
            if self.busy:
                raise WrongState(f"unit {self._s['serial']} is still running")
            self._s = {**self._blank(), "state": "running", "serial": serial, "operator": operator,
                       "procedure": proc, "step": "starting", "started": time.time()}
            self.version += 1
            self._abort.clear()
            self._control = RunControl()
            ask = self.config.confirm if confirm is None else confirm
            self._thread = threading.Thread(target=self._work, args=(serial, operator, proc, ask, None),
                                            name=f"panel-{serial}", daemon=True)
            self._thread.start()
        return self._wait_session(wait_session)

    def _requested_procedure(self, procedure: str | None) -> str:
        """The procedure a start request (page, line) names: the configured one, or another one *by name* from
        the shipped package or a configured folder; never a path (a request does not name code)."""
        from station.engine.procedure import ProcedureError, is_name, resolve_procedure

        configured = self.config.procedure
        if procedure is None or not str(procedure).strip() or procedure == configured:
            return configured
        procedure = str(procedure).strip()
        if Path(configured).suffix == ".py" and procedure == Path(configured).stem:
            return configured
        if not is_name(procedure):
            raise BadProcedure(f"procedure {procedure[:80]!r} is not a procedure name (a request names a shipped "
                             "or configured procedure, never a file)")
        try:
            resolve_procedure(procedure)
        except ProcedureError as e:
            raise BadProcedure(str(e)) from None
        return procedure

    def _procedure_file(self, name: str) -> str | None:
        """The configured procedure file (``--procedure FILE``) when a session ran it by that name."""
        configured = Path(self.config.procedure)
        return str(configured) if configured.suffix == ".py" and configured.stem == name else None

    def check_resumable(self, session: str):
        """The header of a session this panel may resume, else :class:`PanelError` (nothing is loaded): a session
        id in ``$STATION_HOME/sessions`` (never a path), run on this panel's robot, whose procedure is found by
        name where the station's configuration says procedures live, with the journaled sha256."""
        from station.engine.journal import read_journal
        from station.engine.procedure import locate_for_resume
        from station.engine.runner import station_home

        if not session_id_ok(session):
            raise PanelError(f"session {str(session)[:80]!r} is not a session id")
        journal = station_home() / "sessions" / session / "journal.jsonl"
        if not journal.is_file():
            raise PanelError(f"no session {session} on this station")
        try:
            header, _ = read_journal(journal)
            if header.mode != "procedure" or not header.procedure_sha256:
                raise PanelError(f"session {session} has no procedure to resume")
            if header.url != self.config.robot:
                raise PanelError(f"session {session} ran on {header.url}, not on this panel's robot "
                                 f"{self.config.robot}; resume it with station resume")
            locate_for_resume(header.procedure, header.procedure_sha256, file=self._procedure_file(header.procedure),
                              where=f"session {session}")
        except PanelError:
            raise
        except Exception as e:
            raise PanelError(" ".join(str(e).split()) or type(e).__name__) from None
        return header

    def refuse(self, serial: str, operator: str, text: str, procedure: str | None = None, *,
               bad_procedure: bool = False) -> None:
        """A start the line asked for and the station refused before anything ran (a malformed serial, an
        unknown procedure): the verdict ``ERROR`` with the reason, so ``LastResult`` says why. Never while a
        unit runs (that unit's state stays)."""
        with self._lock:
            if self.busy:
                return
            self._s = {**self._blank(), "serial": str(serial or "")[:80] or None, "operator": operator,
                       "procedure": procedure or self.config.procedure, "started": time.time()}
        self._ended_by(refused(text, procedure=bad_procedure), "ERROR", message=text)

    def resume(self, session: str, operator: str | None = None, wait_session: float = 0.0, *,
               confirm: bool | None = None) -> str | None:
        """Continue an interrupted session (a panel crash, an abort, an error) where it stopped; with the
        confirm prompt (unless ``--no-confirm``) before the robot moves again: someone may be in the cell."""
        header = self.check_resumable(session)
        kept = self._kept_samples(header.session)
        with self._lock:
            if self.busy:
                raise WrongState(f"unit {self._s['serial']} is still running")
            self._s = {**self._blank(), "state": "running", "serial": header.serial,
                       "operator": operator or header.operator, "procedure": header.procedure,
                       "session": header.session, "step": "resuming", "started": time.time(),
                       "samples": kept}
            self.version += 1
            self._abort.clear()
            self._control = RunControl()
            ask = self.config.confirm if confirm is None else confirm
            self._thread = threading.Thread(target=self._work, args=(header.serial, operator, header.procedure,
                                                                     ask, header.session),
                                            name=f"panel-resume-{header.serial}", daemon=True)
            self._thread.start()
        return self._wait_session(wait_session)

    def _session_prefix(self) -> str:
        proc = self._s["procedure"] or ""
        name = Path(proc).stem if proc.endswith(".py") else proc
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in self._s["serial"] or "") or "unknown"
        return f"{name}-{safe}-"  # station.engine.runner.new_session_id

    def _find_session(self) -> str | None:
        """The session id of the running unit: the journal folder the engine created after this start."""
        from station.engine.runner import station_home

        with self._lock:
            if self._s["session"]:
                return self._s["session"]
            prefix, since = self._session_prefix(), self._s["started"] - 1.0
        found = [p for p in (station_home() / "sessions").glob(prefix + "*")
                 if (p / "journal.jsonl").is_file() and p.stat().st_mtime >= since]
        if not found:
            return None
        sid = max(found, key=lambda p: p.name).name
        self._set(session=sid)
        return sid

    def _wait_session(self, timeout: float) -> str | None:
        end = time.monotonic() + timeout
        while True:
            sid = self._find_session()
            if sid or time.monotonic() >= end or not self.busy:
                return sid or self._s["session"]
            time.sleep(0.05)

    def abort(self) -> None:
        """ABORT: a move under way stops now (the engine's guarded motion, the driver's stop path), nothing
        moves after it; the session ends ABORTED, journaled, resumable. On the ERROR screen: the operator gives
        the unit up (``ABORTED``; its session stays resumable from the list of interrupted units)."""
        with self._lock:
            if not self.busy and self._s["state"] == "done" and self._s["verdict"] == "ERROR":
                was = self._s["reason"] or "an error"
                rest = (" Its measurements are kept: it can be finished later from the list of interrupted "
                        "units." if self._s["resumable"] else "")
                self._ended_by(Reason(f"Given up by the operator after: {was[:1].lower() + was[1:]}",
                                      "Set the unit aside and scan the next one." + rest,
                                      self._s["detail"] or "", "operator"), "ABORTED",
                               message=self._s["message"], resumable=self._s["resumable"])
                return
            if not self.busy:
                raise WrongState("nothing is running")
            self._abort.set()
            self._s["step"] = "aborting"
            self.version += 1
            self._changed.notify_all()
            control = self._control
        if control is not None:
            control.abort("aborted by the operator")
        self._answer = "abort"
        self._answered.set()

    def answer(self, answer: str) -> None:
        """The operator's answer to the open question, checked like the engine checks it (``Question.check``);
        ``abort`` abandons the run. A refused answer raises ``PromptRefused`` and the question stays open."""
        with self._lock:
            p, q = self._s["prompt"], self._question
            if self._s["state"] != "prompt" or p is None or q is None:
                raise WrongState("no question is open")
            a = str(answer if answer is not None else "").strip()
            if a.lower() == "abort":
                self._answer = "abort"
            else:
                try:
                    q.check(a)
                except BadAnswer as e:
                    raise PromptRefused(str(e)) from None
                self._answer = a
            self._answered.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    # ---- the worker --------------------------------------------------------------------------------
    def ask(self, question: Question | str) -> str:
        """The engine's prompt (``s.ask``, ``ManualTouch``) on the page: blocks the run until the operator gives
        an answer the question accepts; "abort" (or ABORT) interrupts the run."""
        q = question if isinstance(question, Question) else Question(question)
        self._answered.clear()
        self._answer = None
        prompt = {"text": q.text, "kind": q.kind, "choices": ["ok", "abort"] if q.kind == "confirm" else ["abort"],
                  "input": None if q.kind == "confirm" else q.to_dict(), "point": q.point, "image": None,
                  "sketch": None}
        if q.point:
            prompt.update(self.point_urls(q.point))
        with self._lock:
            self._question = q
        self._set(state="prompt", prompt=prompt)
        while not self._answered.wait(0.2):
            if self._abort.is_set():
                break
        answer = self._answer or "abort"
        with self._lock:
            self._question = None
        self._set(state="running", prompt=None)
        if answer == "abort" or self._abort.is_set():
            raise Aborted("aborted by the operator")
        return answer

    def _progress(self, done: int, total: int, text: str) -> None:
        if self._abort.is_set():
            raise Aborted("aborted by the operator")
        if self._s["session"] is None:
            self._find_session()
        self._set(samples=done, samples_planned=total, step=text, **self._residuals())

    def _residuals(self) -> dict:
        """Each recorded sample's residual (``station.panel.residuals``) for the live plot."""
        from station.panel.residuals import live_residuals

        s = self._control.session if self._control is not None else None
        if s is None:
            return {}
        try:
            rows, which = live_residuals(s)
        except Exception as e:  # the plot is a view: a failure to draw it must never stop the unit
            return {"residuals_model": f"not available: {type(e).__name__}: {e}"}
        return {"residuals": rows, "residuals_model": which}

    # ---- the cell's reference points (prompt pictures) -----------------------------------------------
    def cell(self):
        if self._cell is None and self.config.cell:
            from station.engine.cell import load_cell

            self._cell = load_cell(self.config.cell)
        return self._cell

    def point_urls(self, label: str) -> dict:
        """The picture of a point (its ``image:`` in the cell file) or, without one, its generated sketch."""
        from urllib.parse import quote

        cell = self.cell()
        p = cell.points.get(label) if cell is not None else None
        if p is None:
            return {"image": None, "sketch": None}
        base = f"/api/points/{quote(label, safe='')}"
        return {"image": base + "/image" if p.image else None, "sketch": base + "/sketch.svg"}

    def _log(self, text: str) -> None:
        self._set(message=text)

    def _touch(self):
        if self.config.touch != "manual":
            return self.config.touch
        from station.engine import ManualTouch

        return ManualTouch()  # asks through the session's prompt: this page

    def _work(self, serial: str, operator: str, proc: str, confirm: bool, resume_of: str | None) -> None:
        from station import api

        cfg = self.config
        out = None
        try:
            if confirm:
                try:
                    self.ask(f"Unit {serial}: robot clamped, calibration tool mounted, cell clear? "
                             + ("Confirm to move the robot again and finish the unit." if resume_of else
                                "Confirm to start the robot."))
                except Aborted:  # nothing moved, nothing journaled: no empty session is stored
                    self._set(state="idle", step=None, verdict=None, finished=time.time(),
                              message="resume cancelled; the unit can still be resumed" if resume_of else
                              "start cancelled; nothing recorded")
                    return
            self._set(step="connecting")
            if resume_of is None:
                out = api.run(proc, cfg.robot, serial, db=cfg.db, limits=cfg.limits, cell=cfg.cell,
                              operator=operator, options=dict(cfg.options), touch=self._touch(),
                              progress=self._progress, log=self._log, prompt=self.ask, control=self._control)
            else:
                from station.records.store import default_url

                # the panel's own database, never the one a journal names (a journal is data; it may be planted)
                out = api.resume(resume_of, db=cfg.db or default_url(),
                                 touch=None if cfg.touch != "manual" else self._touch(),
                                 progress=self._progress, log=self._log, prompt=self.ask, control=self._control,
                                 procedure=self._procedure_file(proc))
        except Exception as e:  # bad cell/limits file, wrong robot, unreachable bus: before the run's journal
            session = self._s["session"] or resume_of
            can = self._can_resume(session)
            # raised before the run's body: the robot was not (yet) reached in this run
            self._ended_by(explain(e, serial=serial, resumable=can, reached=False), "ERROR",
                           session=session, resumable=can,
                           message=str(e) or type(e).__name__)
            return
        self._conclude(out)

    @staticmethod
    def _kept_samples(session: str) -> int:
        """Samples the session's journal holds (the resumed run's own progress follows)."""
        from station.engine.journal import read_journal
        from station.engine.runner import station_home
        from station.engine.session_record import live_samples

        try:
            _, events = read_journal(station_home() / "sessions" / session / "journal.jsonl")
        except Exception:
            return 0
        return len(live_samples(events))

    def _can_resume(self, session: str | None) -> bool:
        """The unit's session can be continued from this panel (a journal without a completed end)."""
        if not session:
            return False
        try:
            from station.engine import events as ev
            from station.engine.journal import read_journal
            from station.engine.runner import station_home

            self.check_resumable(session)
            _, events = read_journal(station_home() / "sessions" / session / "journal.jsonl")
        except Exception:
            return False
        return not any(isinstance(e, ev.End) and e.status == "completed" for e in events)

    def _conclude(self, out) -> None:
        stored = self._stored(out)
        record = out.record or {}
        verdict_doc = record.get("verdict") or {}
        measurements = verdict_doc.get("measurements") or []
        failing = [plain_failure(m) for m in measurements if m.get("passed") is False]
        if isinstance(record.get("samples"), list):  # the journal's count: a sample recorded after the last
            self._set(samples=len(record["samples"]))  # progress call (the fault came in the next move) counts
        common = {"session": out.session, "failing": failing, "report": str(out.report) if out.report else None,
                  "stored": stored, "measurements": measurements,
                  "parameters": {k: {kk: p.get(kk) for kk in ("value", "std", "unit", "identifiable")}
                                 for k, p in ((record.get("result") or {}).get("parameters") or {}).items()},
                  **self._residuals()}
        if out.status == "interrupted":
            can = self._can_resume(out.session)
            self._ended_by(explain(out.error or Aborted("stopped"), resumable=can), "ABORTED",
                           message=f"{out.error or 'stopped'}; resumable: session {out.session}", resumable=can,
                           **common)
        elif out.passed is not None and not stored:
            why = out.store_error or (str(out.error) if out.error else "the record could not be read back")
            self._ended_by(Reason("The unit finished, but its result could not be saved in the records database.",
                                  "The measurements are kept on this PC. Set the unit aside and call the technician "
                                  "to store the result (station records sync).", why, "setup"), "NOT STORED",
                           message=f"the record is NOT in the database: {why}; the journal keeps everything "
                                   f"(session {out.session}); store it later with station records sync", **common)
        elif out.status == "completed" and out.passed is not None:
            if out.passed:
                self._end(verdict="PASS", reason="Every limit is met; the result is stored.",
                          action="Scan the next unit.", step="finished", **common)
            else:
                n = len(failing)
                self._end(verdict="FAIL", reason=f"{n} limit{'s are' if n != 1 else ' is'} not met — "
                          + "; ".join(failing) + ".", action="Set the unit aside as failed and scan the next unit.",
                          step="finished", **common)
        elif out.status == "completed":  # nothing to judge against: never a PASS
            self._ended_by(Reason("The station has no limits for this robot and procedure, so it cannot decide "
                                  "PASS or FAIL.", "Call the technician (limits file).",
                                  "NO LIMITS: no limit applies to this model and procedure", "setup"), "ERROR",
                           **common)
        else:
            can = self._can_resume(out.session)
            err = out.error
            text = (str(err) if err is not None and str(err) else type(err).__name__)
            self._ended_by(explain(err, serial=self._s["serial"], resumable=can), "ERROR", resumable=can,
                           message=f"{text}; the journal is kept, resumable: session {out.session}", **common)

    def _stored(self, out) -> bool:
        """Read the record back: PASS is shown only for a session the database really holds."""
        if not getattr(out, "stored", False):
            return False
        from station.records import open_records

        try:
            with open_records(out.db if out.db is not None else self.config.db) as rec:
                rec.session(out.session)
            return True
        except Exception:
            return False

    # ---- resumable sessions ------------------------------------------------------------------------
    def resumable(self) -> list[dict]:
        """Interrupted sessions on this station (no completed end in their journal), newest first."""
        from station.engine import events as ev
        from station.engine.journal import read_journal
        from station.engine.runner import station_home

        out = []
        running = self._s.get("session") if self.busy else None
        for j in sorted((station_home() / "sessions").glob("*/journal.jsonl"), key=lambda p: p.stat().st_mtime,
                        reverse=True)[:50]:
            with contextlib.suppress(Exception):
                header, events = read_journal(j)
                if header.session == running or header.session != j.parent.name:
                    continue
                self.check_resumable(header.session)  # only what this panel would resume is offered
                if any(isinstance(e, ev.End) and e.status == "completed" for e in events):
                    continue
                out.append({"session": header.session, "serial": header.serial, "procedure": header.procedure,
                            "operator": header.operator,
                            "samples": sum(1 for e in events if isinstance(e, ev.Sample))})
        return out


def session_id_ok(session) -> bool:
    """A session id (a folder name in ``$STATION_HOME/sessions``), not a path."""
    return isinstance(session, str) and 0 < len(session) <= 200 and not session.startswith(".") and \
        all(c.isalnum() or c in "-_." for c in session)


def report_path(session: str) -> Path | None:
    """The HTML report of a session in ``$STATION_HOME/sessions`` (None: no such file)."""
    from station.engine.runner import station_home

    if not session_id_ok(session):
        return None
    p = station_home() / "sessions" / session / "report.html"
    return p if p.is_file() else None
