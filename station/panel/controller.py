"""One station, one unit at a time: the state machine behind the operator panel and the OPC UA server.

It runs the same engine as ``station run`` (``station.api.run`` / ``station.api.resume``, with a progress
callback) in a worker thread, asks the operator through prompts, and reports a verdict only once the session
record has been read back from the records database (never PASS unless stored: a record that did not store
ends as ``NOT STORED``; the journal keeps everything and can be stored later)."""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from station.engine.procedure import BadAnswer, Question
from station.engine.runner import Aborted, RunControl

STATES = ("idle", "running", "prompt", "done")


class PanelError(ValueError):
    """A request the station refuses (wrong state, bad input); the API answers 409/400 with its text."""


class WrongState(PanelError):
    """A request the station's present state refuses (a unit running, nothing running, no question open): 409."""


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


def plain_failure(m: dict) -> str:
    """A failing verdict measurement in words an operator can act on."""
    name = str(m.get("name") or "?").replace("_", " ")
    value, unit = m.get("value"), m.get("unit") or ""
    lo, hi = m.get("low"), m.get("high")
    if value is None:
        return f"{name}: no value could be measured"
    v = f"{float(value):.4g} {unit}".strip()
    if hi is not None and float(value) > float(hi):
        return f"{name} is {v}, above the limit of {float(hi):.4g} {unit}".strip()
    if lo is not None and float(value) < float(lo):
        return f"{name} is {v}, below the limit of {float(lo):.4g} {unit}".strip()
    return f"{name} is {v}, outside its limits"


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

    # ---- state ---------------------------------------------------------------------------------------
    @staticmethod
    def _blank() -> dict:
        return {"state": "idle", "serial": None, "operator": None, "procedure": None, "step": None,
                "samples": 0, "samples_planned": 0, "verdict": None, "session": None, "failing": [],
                "message": None, "prompt": None, "report": None, "stored": None, "result": None,
                "started": None, "finished": None, "residuals": [], "residuals_model": None}

    def _set(self, **kw) -> None:
        with self._lock:
            self._s.update(kw)
            self.version += 1
            self._changed.notify_all()

    def snapshot(self) -> dict:
        with self._lock:
            out = {k: v for k, v in self._s.items() if k != "result"}
            out["progress"] = (out["samples"] / out["samples_planned"]) if out["samples_planned"] else 0.0
            out["version"] = self.version
            return out

    def last_result(self) -> dict | None:
        """The finished unit's summary (verdict, measurements, parameters) for the line (OPC UA LastResult)."""
        with self._lock:
            return self._s["result"]

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
            raise PanelError(f"procedure {procedure[:80]!r} is not a procedure name (a request names a shipped "
                             "or configured procedure, never a file)")
        try:
            resolve_procedure(procedure)
        except ProcedureError as e:
            raise PanelError(str(e)) from None
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

    def resume(self, session: str, operator: str | None = None, wait_session: float = 0.0) -> str | None:
        """Continue an interrupted session (a panel crash, an abort) where it stopped."""
        header = self.check_resumable(session)
        with self._lock:
            if self.busy:
                raise WrongState(f"unit {self._s['serial']} is still running")
            self._s = {**self._blank(), "state": "running", "serial": header.serial,
                       "operator": operator or header.operator, "procedure": header.procedure,
                       "session": header.session, "step": "resuming", "started": time.time()}
            self.version += 1
            self._abort.clear()
            self._control = RunControl()
            self._thread = threading.Thread(target=self._work, args=(header.serial, operator, header.procedure,
                                                                     False, header.session),
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
        moves after it; the session ends ABORTED, journaled, resumable."""
        with self._lock:
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
                             "Confirm to start the robot.")
                except Aborted:  # nothing moved, nothing journaled: no empty session is stored
                    self._set(state="idle", step=None, verdict=None, message="start cancelled; nothing recorded",
                              finished=time.time())
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
        except Exception as e:  # bad cell/limits file, wrong robot, unreachable bus: said in one line
            self._set(state="done", verdict="ERROR", message=f"{type(e).__name__}: {e}" if not str(e) else str(e),
                      step="stopped", finished=time.time())
            return
        self._conclude(out)

    def _conclude(self, out) -> None:
        stored = self._stored(out)
        verdict_doc = (out.record or {}).get("verdict") or {}
        failing = [plain_failure(m) for m in verdict_doc.get("measurements") or [] if m.get("passed") is False]
        report = str(out.report) if out.report else None
        if out.status == "interrupted":
            verdict, msg = "ABORTED", f"{out.error or 'stopped'}; resumable: session {out.session}"
        elif out.passed is not None and not stored:
            verdict = "NOT STORED"
            msg = ("the record is NOT in the database" + (f": {out.error}" if out.error else "")
                   + f"; the journal keeps everything (session {out.session}); store it later with "
                     "station records sync")
        elif out.status == "completed" and out.passed is not None:
            verdict, msg = ("PASS" if out.passed else "FAIL"), None
        else:
            err = out.error
            verdict = "ERROR"
            msg = (f"{err}" if err is not None and str(err) else type(err).__name__) + \
                f"; the journal is kept, resumable: session {out.session}"
        result = {"session": out.session, "serial": self._s["serial"], "procedure": self._s["procedure"],
                  "verdict": verdict, "stored": stored, "failing": failing, "report": report,
                  "measurements": verdict_doc.get("measurements") or [],
                  "parameters": {k: {kk: p.get(kk) for kk in ("value", "std", "unit", "identifiable")}
                                 for k, p in (((out.record or {}).get("result") or {}).get("parameters") or {})
                                 .items()}}
        self._set(state="done", verdict=verdict, session=out.session, failing=failing, report=report,
                  stored=stored, message=msg, result=result, step="finished", finished=time.time(),
                  **self._residuals())

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
