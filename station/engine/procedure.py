"""Procedure files: a short Python module whose ``checklist(s)`` reads like the technician's checklist.

A procedure file defines::

    \"\"\"One-line title.  Longer description.\"\"\"
    IDENTIFY = "offsets"            # optional constants the checklist uses
    def checklist(s):               # s: station.engine.Session
        s.connect()
        ...

Shipped procedures live in ``procedures/`` (import name ``station.procedures``, package data of the wheel,
found through ``importlib.resources``) and are found by name; any other file is given by path. The file's
SHA-256 goes into the journal header; a resume refuses a changed file."""

from __future__ import annotations

import hashlib
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
