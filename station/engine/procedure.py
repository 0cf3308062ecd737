"""Procedure files: a short Python module whose ``checklist(s)`` reads like the technician's checklist.

A procedure file defines::

    \"\"\"One-line title.  Longer description.\"\"\"
    IDENTIFY = "offsets"            # optional constants the checklist uses
    @measures(*SOLVE, judged=("samples", "fit_rms"))   # what it measures (station.engine.declare)
    @takes(*PLAN_OPTIONS)           # the options it takes (station run builds its flags from them)
    def checklist(s):               # s: station.engine.Session
        s.connect()
        ...

Shipped procedures live in ``procedures/`` (import name ``station.procedures``, package data of the wheel,
found through ``importlib.resources``); a site's own procedures live in the folders ``$STATION_PROCEDURES``
lists (the station's configuration). Both are found by name (:func:`resolve_procedure`); a file given by path
on the station's own command line (``station run my.py``) is used as given. The journal records the name,
version and SHA-256 of the procedure; a resume finds it again *by name* in those places (never by a path a
journal, a cell file or a request names) and refuses, before any import, one that is not there or whose SHA-256
differs (:func:`procedure_for_resume`).

A checklist asks the operator through ``s.ask(Question(...))`` (confirm, a number with unit and range, a text
matching a pattern, a choice): the one prompt API of the engine. The front end (the terminal's
:func:`terminal_prompt`, the operator panel) validates as the operator types; the session checks the answer
again with :meth:`Question.check` whatever front end gave it."""

from __future__ import annotations

import ast
import hashlib
import math
import os
import re
import sys
import types
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from station.robot.errors import ConfigError

PROCEDURES_ENV = "STATION_PROCEDURES"
# a procedure's name: a Python-like file stem, never a path (no separator, no dot, no leading underscore)
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


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
    version: str | None = None  # the file's ``VERSION = "..."``; a shipped one without it: the station's version

    def checklist(self, s) -> None:
        self.module.checklist(s)

    @property
    def defaults(self) -> dict:
        return dict(getattr(self.module, "DEFAULTS", {}) or {})

    @property
    def measurements(self):
        """What the checklist declares it measures (``station.engine.declare.measures``); None: it declares
        nothing (then nothing is checked against the limits file)."""
        from station.engine.declare import declared_measurements

        return declared_measurements(self.module.checklist)

    @property
    def options(self):
        """The options the checklist declares it takes (``station.engine.declare.takes``); None: undeclared."""
        from station.engine.declare import declared_options

        return declared_options(self.module.checklist)

    @property
    def identify(self) -> str | None:
        """The parameter group the procedure solves for (its ``IDENTIFY``); None: it does not solve, so
        ``--identify`` does not apply to it."""
        value = getattr(self.module, "IDENTIFY", None)
        return str(value) if value else None


def shipped_names() -> list[str]:
    return sorted(p.stem for p in shipped_folder().glob("*.py") if NAME.fullmatch(p.stem))


def procedure_folders() -> list[Path]:
    """The site's procedure folders, as the station's configuration lists them (``$STATION_PROCEDURES``,
    separated by ``os.pathsep``), in order. Only absolute folders count: a relative one would depend on where a
    command happens to be started."""
    out = []
    for part in os.environ.get(PROCEDURES_ENV, "").split(os.pathsep):
        p = Path(part.strip()).expanduser() if part.strip() else None
        if p is not None and p.is_absolute() and p not in out:
            out.append(p)
    return out


def is_name(text: str) -> bool:
    """A procedure name (looked up in the shipped package and the configured folders), not a file path."""
    return bool(NAME.fullmatch(str(text)))


def resolve_procedure(name: str) -> Path:
    """The procedure file of ``name``: the shipped package's (a site folder cannot shadow a shipped procedure),
    else the first of the configured folders (:func:`procedure_folders`) that has ``NAME.py``. Raises
    :class:`ProcedureError` for a name that is not a procedure name or is found nowhere."""
    if not is_name(name):
        raise ProcedureError(f"procedure {str(name)[:80]!r} is not a procedure name (letters, digits, _ and -; "
                             "procedures are found by name, never by a path a file or a request gives)")
    for folder in (shipped_folder(), *procedure_folders()):
        cand = folder / f"{name}.py"
        if cand.is_file():
            return cand
    folders = procedure_folders()
    where = f"${PROCEDURES_ENV}: {os.pathsep.join(map(str, folders))}" if folders else f"${PROCEDURES_ENV} is not set"
    raise ProcedureError(f"unknown procedure {name!r}; shipped: {', '.join(shipped_names())}; site folders "
                         f"({where})")


def find_procedure(name_or_path: str) -> Path:
    """A procedure name (:func:`resolve_procedure`) or, on the station's own command line, a ``.py`` file."""
    if is_name(name_or_path):
        return resolve_procedure(name_or_path)
    p = Path(name_or_path)
    if p.suffix != ".py":
        raise ProcedureError(f"unknown procedure {name_or_path!r}; shipped: {', '.join(shipped_names())} "
                             "(or give a .py file)")
    if not p.is_file():
        raise ProcedureError(f"procedure file {p} does not exist")
    return p


def load_procedure(name_or_path: str | Path) -> Procedure:
    path = find_procedure(str(name_or_path))
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ProcedureError(f"procedure {path}: {e.strerror or e}") from None
    return _load(path, data)


def locate_for_resume(name: str, sha256: str, *, file: str | Path | None = None,
                      where: str = "the session") -> tuple[Path, bytes]:
    """Where the procedure a session ran is now, and its bytes, checked against the journaled SHA-256; nothing
    is compiled or run. ``file``: the procedure file the station's own command line names (``station resume
    --procedure FILE``, the panel's ``--procedure FILE``; its stem must be ``name``); else ``name`` is looked up
    in the shipped package and the configured folders (:func:`resolve_procedure`). Never a path from a journal."""
    if not is_name(name):
        raise ProcedureError(f"{where}: procedure {str(name)[:80]!r} is not a procedure name; not resumed "
                             "(nothing was loaded)")
    if file is not None:
        path = Path(file)
        if path.suffix != ".py" or path.stem != name:
            raise ProcedureError(f"--procedure {path}: {where} ran procedure {name!r}; give its file {name}.py")
    else:
        path = resolve_procedure(name)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ProcedureError(f"procedure {path}: {e.strerror or e}") from None
    if hashlib.sha256(data).hexdigest() != sha256:
        raise ProcedureError(f"procedure {name} ({path}) is not the one {where} started with (sha256 differs); "
                             "resuming would mix two procedures (nothing was loaded)")
    return path, data


def procedure_for_resume(name: str, sha256: str, *, file: str | Path | None = None,
                         where: str = "the session") -> Procedure:
    """The procedure a session ran, found again to resume it (:func:`locate_for_resume`). Exactly the bytes
    that were hashed are compiled and run: a procedure that is not found, or whose SHA-256 is not the journaled
    one, never runs."""
    path, data = locate_for_resume(name, sha256, file=file, where=where)
    return _load(path, data)


def declared_version(data: bytes) -> str | None:
    """The ``VERSION = "..."`` string a procedure file declares at module level, read without running it."""
    try:
        tree = ast.parse(data)
    except (SyntaxError, ValueError):
        return None
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "VERSION" for t in node.targets) \
                and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            return node.value.value[:64]
    return None


def _station_version() -> str | None:
    from importlib import metadata

    try:
        return metadata.version("station")
    except metadata.PackageNotFoundError:
        return None


def _check_declarations(path: Path, checklist) -> None:
    """``@measures``/``@takes`` hold what they say (a procedure that sets the attributes by hand is checked too)."""
    from station.engine.declare import Measurement, Option, declared_measurements, declared_options

    for what, attr, items, kind in (("measures", "measurements", declared_measurements(checklist), Measurement),
                                    ("takes", "options", declared_options(checklist), Option),
                                    ("takes", "settings", getattr(checklist, "settings", None), Option)):
        if items is not None and not (isinstance(items, tuple) and all(isinstance(x, kind) for x in items)):
            raise ProcedureError(f"procedure {path}: checklist.{attr} must be declared with @{what}(...) of "
                                 "station.engine.declare")


def _load(path: Path, data: bytes) -> Procedure:
    """Compile and run exactly ``data`` (the bytes that were hashed) as the procedure module of ``path``."""
    try:
        code = compile(data, str(path), "exec")
    except (SyntaxError, ValueError) as e:
        line = getattr(e, "lineno", None)
        raise ProcedureError(f"procedure {path}" + (f" line {line}" if line else "") + f": {getattr(e, 'msg', e)}") \
            from None
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
    _check_declarations(path, fn)
    doc = (module.__doc__ or "").strip()
    if not doc:
        raise ProcedureError(f"procedure {path}: needs a docstring saying what it calibrates")
    version = declared_version(data)
    if version is None and path.parent.resolve() == shipped_folder().resolve():
        version = _station_version()
    # the name is the file's stem: resume finds the procedure again by it, before anything is imported
    return Procedure(name, path, hashlib.sha256(data).hexdigest(), doc.splitlines()[0], module, version)
