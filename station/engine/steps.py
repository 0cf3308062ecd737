"""Steps: what a session is doing, traced the way labgrid traces its ``@step`` methods.

A step has a name and its arguments; it starts, and it ends ``done`` or ``failed`` (with the exception) after a
measured duration, or it is ``skipped`` with a reason. Steps nest: a session keeps the stack of the steps
running now, so a fault, an abort or a stopped move is named after the innermost one (``approach`` of pose 3),
never after a guess. Every start and end is one ``step`` event in the session journal (fsynced like any
event); ``station.engine.session_record`` projects them into the record, where the report and ``station
records show`` list them.

Two ways to open a step, one mechanism: ``with s.step("solve", identify=...)`` around a block, or the
decorator on a function whose first argument is the session (a ``Session`` method or a procedure's helper)::

    @step(args=("pose",))
    def approach(s, pose): ...

Pure Python: no numpy, no robot."""

from __future__ import annotations

import contextlib
import functools
import inspect
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from station.engine import events as ev

MESSAGE_MAX = 500  # characters of an exception's text kept in a failed step's event


@dataclass
class RunningStep:
    """A step that started and has not ended yet (``Steps.current``), or the one a failure came out of."""

    name: str
    info: dict
    parent: RunningStep | None = None
    started: float = field(default_factory=time.monotonic)

    @property
    def pose(self) -> int | None:
        """The plan pose the step works on (its ``pose`` argument), if any."""
        pose = self.info.get("pose")
        return pose if isinstance(pose, int) and not isinstance(pose, bool) else None

    def describe(self) -> str:
        """``approach of pose 3``, or the name alone."""
        return self.name if self.pose is None else f"{self.name} of pose {self.pose}"


class Steps:
    """The steps of one session: the stack of running ones and where their events go.

    ``journal(event)`` writes one event (``Session.event``). ``on_lost(name, error)``: what to do when a step's
    event cannot be written (disk full): None raises (a procedure stops: its trace is part of the record);
    a technician's session passes a callback, so that an action the technician asked for (hold the arm stiff)
    is never held back by its trace. Either way the journal lists the lost event and the session cannot
    PASS."""

    def __init__(self, journal: Callable[[ev.Event], Any],
                 on_lost: Callable[[str, Exception], None] | None = None) -> None:
        self._journal = journal
        self.on_lost = on_lost
        self._stack: list[RunningStep] = []
        self.failed: RunningStep | None = None  # the innermost step the last failure came out of
        self._failure: BaseException | None = None
        self.last: RunningStep | None = None  # the step that ended last

    @property
    def current(self) -> RunningStep | None:
        """The innermost running step (None between steps)."""
        return self._stack[-1] if self._stack else None

    def failed_for(self, error: BaseException | None) -> RunningStep | None:
        """The innermost step ``error`` came out of (None when it was raised outside every step)."""
        return self.failed if error is not None and error is self._failure else None

    @contextlib.contextmanager
    def run(self, name: str, info: dict | None = None) -> Iterator[RunningStep]:
        """Journal the start (with the arguments), run the block, journal ``done`` or ``failed`` with the
        duration. The block's exception is re-raised as it was, even if its ``failed`` event cannot be
        written."""
        step = RunningStep(name, ev._plain(dict(info or {})), self.current)
        self._write(ev.Step(name=name, status="start", info=step.info), name)
        self._stack.append(step)
        step.started = time.monotonic()
        try:
            yield step
        except BaseException as e:
            self._end(step)
            if e is not self._failure:  # the innermost step claims it; the steps around it re-raise it
                self.failed, self._failure = step, e
            with contextlib.suppress(Exception):  # the fault itself is what the run reports
                self._write(ev.Step(name=name, status="failed", error=type(e).__name__,
                                    message=(str(e) or type(e).__name__)[:MESSAGE_MAX],
                                    duration=time.monotonic() - step.started), name)
            raise
        self._end(step)
        self._write(ev.Step(name=name, status="done", duration=time.monotonic() - step.started), name)

    def skip(self, name: str, reason: str, info: dict | None = None) -> None:
        """A step the session decided not to run (``write_back`` without ``--apply``), with the reason."""
        self._write(ev.Step(name=name, status="skipped", reason=reason, info=ev._plain(dict(info or {}))), name)

    def _end(self, step: RunningStep) -> None:
        while self._stack and self._stack[-1] is not step:  # a generator step left open by its caller
            self._stack.pop()
        if self._stack:
            self._stack.pop()
        self.last = step

    def _write(self, event: ev.Step, name: str) -> None:
        if self.on_lost is None:
            self._journal(event)
            return
        try:
            self._journal(event)
        except Exception as e:  # the journal (disk) failed: the technician's action goes on, said aloud
            self.on_lost(name, e)


def _arg(value):
    """A step argument as the journal keeps it: a planned pose by its index, a reference point by its label,
    a path as text; plain values as they are."""
    index = getattr(value, "index", None)
    if isinstance(index, int) and hasattr(value, "approach_q"):  # station.engine.plan.PlannedPose
        return index
    label = getattr(value, "label", None)
    if isinstance(label, str):
        return label
    if isinstance(value, (str, int, float, bool, type(None), list, tuple, dict)):
        return value
    return str(value)


def step(name: str | None = None, *, args: tuple[str, ...] = ()):
    """Make a function a step of the session passed as its first argument (``self`` of a ``Session`` method,
    ``s`` of a procedure's helper): journaled under ``name`` (default: the function's name) with the
    arguments named in ``args`` (as called, defaults applied; None left out)."""

    def decorator(func):
        title = name or func.__name__
        signature = inspect.signature(func)
        first = next(iter(signature.parameters))

        @functools.wraps(func)
        def wrapper(*a, **kw):
            bound = signature.bind_partial(*a, **kw)
            bound.apply_defaults()
            info = {k: _arg(bound.arguments[k]) for k in args if bound.arguments.get(k) is not None}
            with bound.arguments[first].step(title, **info):
                return func(*a, **kw)

        return wrapper

    return decorator


# ---- the steps of a journal, as the record keeps them ------------------------------------------------------
def summarize(events: list[ev.Event], when: Callable[[float | None], Any] = lambda t: t) -> list[dict]:
    """The steps of a session's events, one entry per step name and the step it ran in (``parent``, None for a
    step of the checklist itself), in the order each first ran: ``runs``, how many ended
    ``done``/``failed``/``skipped`` and how many never ended (``unfinished``: the process died, or the session is
    still running), ``duration_s`` (the ended runs' total), ``started`` (host time of the first start, as
    ``when`` writes it), ``depth`` (how many steps it ran in), ``info`` (the arguments, when it ran once) and
    ``not_done`` (every run that did not end done: its arguments and why). A ``resume`` event ends every step
    still open before it as unfinished."""
    table = _StepTable(when)
    for event in events:
        if isinstance(event, ev.Resume):
            table.close_all()
        if isinstance(event, ev.Step):
            table.add(event)
    table.close_all()
    return table.entries()


class _StepTable:
    """The running tally behind :func:`summarize`: the entries so far and the steps still open."""

    def __init__(self, when: Callable[[float | None], Any]) -> None:
        self.when = when
        self.out: dict[tuple, dict] = {}
        self.open: list[tuple[tuple, dict, float | None]] = []  # (key, info, t) of the steps running, outermost first

    def entry(self, name: str, info: dict, t: float | None) -> tuple:
        parent = self.open[-1][0][1] if self.open else None
        key = (parent, name)
        if key not in self.out:
            self.out[key] = {"name": name, "parent": parent, "runs": 0, "done": 0, "failed": 0, "skipped": 0,
                             "unfinished": 0, "duration_s": 0.0, "started": self.when(t), "depth": len(self.open),
                             "info": info, "not_done": []}
        self.out[key]["runs"] += 1
        return key

    def unfinished(self, key: tuple, info: dict, t: float | None) -> None:
        self.out[key]["unfinished"] += 1
        self.out[key]["not_done"].append({"status": "unfinished", "info": info, "started": self.when(t)})

    def close_all(self) -> None:
        """Every step still open ends unfinished (a resume: the process that ran them died)."""
        while self.open:
            self.unfinished(*self.open.pop())

    def add(self, event: ev.Step) -> None:
        info = dict(event.info)
        if event.status == "start":
            self.open.append((self.entry(event.name, info, event.t), info, event.t))
        elif event.status == "skipped":
            key = self.entry(event.name, info, event.t)
            self.out[key]["skipped"] += 1
            self.out[key]["not_done"].append({"status": "skipped", "info": info, "reason": event.reason,
                                              "started": self.when(event.t)})
        elif any(key[1] == event.name for key, _, _ in self.open):
            self.end(event)

    def end(self, event: ev.Step) -> None:
        while self.open[-1][0][1] != event.name:  # an inner step whose end was never written
            self.unfinished(*self.open.pop())
        key, info, t = self.open.pop()
        e = self.out[key]
        e[event.status] += 1
        e["duration_s"] += event.duration or 0.0
        if event.status == "failed":
            e["not_done"].append({"status": "failed", "info": info, "started": self.when(t), "error": event.error,
                                  "message": event.message})

    def entries(self) -> list[dict]:
        for e in self.out.values():
            if e["runs"] != 1:
                e["info"] = {}  # several runs ran with several arguments: no one of them is the step's
        return list(self.out.values())
