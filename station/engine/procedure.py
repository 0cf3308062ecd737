"""Procedure files: a short Python module whose ``checklist(s)`` reads like the technician's checklist.

A procedure file defines::

    \"\"\"One-line title.  Longer description.\"\"\"
    IDENTIFY = "offsets"            # optional constants the checklist uses
    def checklist(s):               # s: station.engine.Session
        s.connect()
        ...

Shipped procedures live in ``procedures/`` (import name ``station.procedures``, package data of the wheel,
found through ``importlib.resources``) and are found by name; any other file is given by path. The file's
SHA-256 goes into the journal header; a resume refuses a changed file.

A checklist asks the operator through ``s.ask(Question(...))`` (confirm, a number with unit and range, a text
matching a pattern, a choice): the one prompt API of the engine. The front end (the terminal's
:func:`terminal_prompt`, the operator panel) validates as the operator types; the session checks the answer
again with :meth:`Question.check` whatever front end gave it."""

from __future__ import annotations

import hashlib
import math
import re
import sys
import types
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from station.robot.errors import ConfigError


def shipped_folder() -> Path:
    """The folder of the shipped procedures and default limits (``station.procedures``), wherever the package
    is installed (source tree, editable or wheel install)."""
    return Path(str(resources.files("station.procedures")))



class ProcedureError(ConfigError):
    """A procedure file is missing or broken; the message names the file and line."""


class BadAnswer(ValueError):
    """An answer a question refuses; the text is the one-line reason shown to the operator."""


class Abandoned(KeyboardInterrupt):
    """The operator aborted at a prompt (or the prompt could not be answered): the run stops as on Ctrl-C,
    resumable."""


KINDS = ("confirm", "number", "text", "choice")


class Question(str):
    """What a checklist asks the operator. It *is* its text (a ``str``), so a prompt callable written for plain
    text keeps working; front ends that can do more read the fields:

    - ``kind``: ``confirm`` (OK/abort), ``number`` (``unit``, ``low``/``high`` in that unit, both optional),
      ``text`` (``pattern``: a regular expression the whole answer must match), ``choice`` (``choices``);
    - ``point``: the cell's reference point it is about (the panel shows its image, else a sketch);
    - ``key``: a name for the answer: it is journaled under it, and a resumed session reuses it (not asked
      again)."""

    kind: str
    unit: str | None
    low: float | None
    high: float | None
    pattern: str | None
    choices: tuple[str, ...]
    point: str | None
    key: str | None

    def __new__(cls, text: str, kind: str = "confirm", *, unit: str | None = None, low: float | None = None,
                high: float | None = None, pattern: str | None = None, choices=None, point: str | None = None,
                key: str | None = None) -> Question:
        self = super().__new__(cls, str(text))
        if kind not in KINDS:
            raise ConfigError(f"question {text!r}: kind must be one of {', '.join(KINDS)}, got {kind!r}")
        self.kind, self.unit, self.point, self.key = kind, unit or None, point, key
        self.low = None if low is None else float(low)
        self.high = None if high is None else float(high)
        self.pattern = pattern
        self.choices = tuple(str(c) for c in (choices or ()))
        if kind == "text" and pattern is not None:
            try:
                re.compile(pattern)
            except re.error as e:
                raise ConfigError(f"question {text!r}: pattern {pattern!r} is not a regular expression: {e}") \
                    from None
        if kind == "choice" and not self.choices:
            raise ConfigError(f"question {text!r}: a choice needs choices")
        if self.low is not None and self.high is not None and self.low > self.high:
            raise ConfigError(f"question {text!r}: low {self.low:g} is above high {self.high:g}")
        return self

    @property
    def text(self) -> str:
        return str.__str__(self)

    def hint(self) -> str:
        """What the operator may type, in words (shown by the terminal and the panel)."""
        if self.kind == "number":
            u = f" {self.unit}" if self.unit else ""
            if self.low is not None and self.high is not None:
                return f"a number from {self.low:g} to {self.high:g}{u}"
            if self.low is not None:
                return f"a number of at least {self.low:g}{u}"
            if self.high is not None:
                return f"a number of at most {self.high:g}{u}"
            return f"a number{(' in' + u) if u else ''}"
        if self.kind == "text":
            return f"text matching {self.pattern}" if self.pattern else "text"
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        return "confirm"

    def to_dict(self) -> dict:
        """The question as JSON (the panel's ``prompt.input``); ``units``: the units an answer may be typed in,
        each with its factor to ``unit``."""
        fam = self._family()
        units = {u: k / fam[self.unit] for u, k in fam.items()} if fam else {}
        return {"kind": self.kind, "unit": self.unit, "low": self.low, "high": self.high, "pattern": self.pattern,
                "choices": list(self.choices), "hint": self.hint(), "key": self.key, "units": units}

    def _family(self) -> dict[str, float] | None:
        from station.units import ANGLE_UNITS, LENGTH_UNITS

        return next((f for f in (LENGTH_UNITS, ANGLE_UNITS) if self.unit in f), None)

    def check(self, answer) -> str | float:
        """The value of a valid answer (a number: SI when ``unit`` is a length or angle unit, else in ``unit``;
        a text or choice as given; ``"ok"`` for a confirm). Raises :class:`BadAnswer` with a one-line reason."""
        a = str(answer if answer is not None else "").strip()
        if self.kind == "confirm":
            if a.lower() in ("", "ok", "yes", "y"):
                return "ok"
            raise BadAnswer(f"answer ok or abort, not {a!r}")
        if not a:
            raise BadAnswer(f"an answer is required: {self.hint()}")
        if self.kind == "number":
            return self._number(a)
        if self.kind == "choice":
            for c in self.choices:
                if a.lower() == c.lower():
                    return c
            raise BadAnswer(f"{a!r} is not {self.hint()}")
        if self.pattern is not None and re.fullmatch(self.pattern, a) is None:
            raise BadAnswer(f"{a!r} does not match {self.pattern}")
        if len(a) > 1000:
            raise BadAnswer("the answer is longer than 1000 characters")
        return a

    def _number(self, a: str) -> float:
        m = re.fullmatch(r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z%]*)", a)
        if m is None:
            raise BadAnswer(f"{a!r} is not a number; expected {self.hint()}")
        x, typed = float(m.group(1)), m.group(2) or None
        family = self._family()
        if typed is not None and typed != self.unit:
            if family is None or typed not in family:
                raise BadAnswer(f"{a!r}: the unit must be {self.unit or 'none'}")
            x = x * family[typed] / family[self.unit]
        if not math.isfinite(x):
            raise BadAnswer(f"{a!r} is not a finite number")
        if (self.low is not None and x < self.low) or (self.high is not None and x > self.high):
            raise BadAnswer(f"{x:g}{(' ' + self.unit) if self.unit else ''} is out of range: expected {self.hint()}")
        return x * family[self.unit] if family is not None else x


def terminal_prompt(q: str) -> str:
    """``station run``'s prompt: asks on the terminal until the answer is valid (the reason of a refusal is
    printed, the question asked again); ``abort`` or the end of input abandons the run."""
    q = q if isinstance(q, Question) else Question(q)
    hint = " [Enter] " if q.kind == "confirm" else f" ({q.hint()}): "
    while True:
        try:
            a = input(q.text + hint)
        except EOFError:
            raise Abandoned("no answer: standard input is closed") from None
        if a.strip().lower() == "abort":
            raise Abandoned("aborted at the prompt")
        try:
            q.check(a)
            return a
        except BadAnswer as e:
            print(f"station: {e}", file=sys.stderr)


@dataclass(frozen=True)
class Procedure:
    name: str
    path: Path
    sha256: str
    title: str
    module: types.ModuleType

    def checklist(self, s) -> None:
        self.module.checklist(s)

    @property
    def defaults(self) -> dict:
        return dict(getattr(self.module, "DEFAULTS", {}) or {})

    @property
    def identify(self) -> str | None:
        """The parameter group the procedure solves for (its ``IDENTIFY``); None: it does not solve, so
        ``--identify`` does not apply to it."""
        value = getattr(self.module, "IDENTIFY", None)
        return str(value) if value else None


def shipped_names() -> list[str]:
    return sorted(p.stem for p in shipped_folder().glob("*.py") if not p.name.startswith("_"))


def find_procedure(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".py" or p.exists():
        if not p.is_file():
            raise ProcedureError(f"procedure file {p} does not exist")
        return p
    cand = shipped_folder() / f"{name_or_path}.py"
    if not cand.is_file() or name_or_path.startswith("_"):
        raise ProcedureError(f"unknown procedure {name_or_path!r}; shipped: {', '.join(shipped_names())} "
                             "(or give a .py file)")
    return cand


def load_procedure(name_or_path: str | Path) -> Procedure:
    path = find_procedure(str(name_or_path))
    data = path.read_bytes()
    try:
        code = compile(data, str(path), "exec")
    except SyntaxError as e:
        raise ProcedureError(f"procedure {path} line {e.lineno}: {e.msg}") from None
    name = path.stem
    module = types.ModuleType(f"station.procedures._loaded.{name}")
    module.__file__ = str(path)
    try:
        exec(code, module.__dict__)
    except Exception as e:  # a procedure that fails at import is a broken file: say where
        tb = e.__traceback__
        line = None
        while tb is not None:
            if tb.tb_frame.f_code.co_filename == str(path):
                line = tb.tb_lineno
            tb = tb.tb_next
        where = f" line {line}" if line else ""
        raise ProcedureError(f"procedure {path}{where}: {type(e).__name__}: {e}") from None
    fn = module.__dict__.get("checklist")
    if not callable(fn):
        raise ProcedureError(f"procedure {path}: defines no checklist(s) function")
    doc = (module.__doc__ or "").strip()
    if not doc:
        raise ProcedureError(f"procedure {path}: needs a docstring saying what it calibrates")
    return Procedure(str(getattr(module, "NAME", name)), path, hashlib.sha256(data).hexdigest(),
                     doc.splitlines()[0], module)
