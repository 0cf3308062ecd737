"""Outputs that a factory script can trust and inputs that cannot hang the station.

- ``write_atomic``: write a temporary file next to the destination, fsync, rename; never onto an input file
  of the same command; an unwritable destination is one line and leaves no ``.tmp`` behind.
- ``dumps_json``: always valid JSON (``allow_nan=False``; a NaN/Infinity is ``null``, the field's reason says
  why). The one JSON writer of the station's files: results, records, the journal, correction maps.
- ``read_json``: a regular file of bounded size, NaN/Infinity and deep nesting refused, one line naming
  the file. Errors are ``ConfigError`` (exit 2).

Only the standard library at module level: the solver (map files), records and journal use ``dumps_json``
without loading the robot package or YAML."""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path

MAX_JSON_BYTES = 64 * 1024 * 1024  # a calibration result with a covariance of a few hundred parameters is < 10 MB


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def check_destination(path: str | Path, inputs: dict | None = None, option: str = "--out") -> None:
    """``ConfigError`` if ``path`` cannot take an output: an input file of the command, a directory, a missing
    folder or one the station may not write to. Call it before the work so nothing is computed in vain."""
    from station.robot.errors import ConfigError

    path = Path(path)
    for opt, p in (inputs or {}).items():
        if p is not None and _same_file(path, Path(p)):
            raise ConfigError(f"{option} {path}: is the {opt} input file; refusing to overwrite it")
    if path.is_dir():
        raise ConfigError(f"{option} {path}: is a directory; give a file name")
    if not path.parent.is_dir():
        raise ConfigError(f"{option} {path}: folder {path.parent} does not exist")
    if not os.access(path.parent, os.W_OK):
        raise ConfigError(f"{option} {path}: folder {path.parent} is not writable")


def write_atomic(path: str | Path, text: str, inputs: dict[str, str | Path | None] | None = None,
                 option: str = "--out") -> None:
    """Write ``text`` to ``path`` atomically. ``inputs`` (option -> path) are the command's input files:
    writing over one of them is refused before anything is written."""
    from station.robot.errors import ConfigError

    path = Path(path)
    check_destination(path, inputs, option)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise ConfigError(f"{option} {path}: cannot write ({e.strerror or e})") from None


def _clean(x):
    """``x`` with every non-finite float replaced by None (JSON has no NaN); numpy arrays and scalars become
    plain lists and numbers (first, so a numpy NaN is caught too), tuples and sets lists."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, str | int | bool | None):
        return x
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple | set | frozenset):
        return [_clean(v) for v in x]
    if hasattr(x, "tolist"):  # numpy array or scalar (no numpy import here)
        return _clean(x.tolist())
    return x


def dumps_json(doc, indent: int | None = 2, *, compact: bool = False, default=None) -> str:
    """Valid JSON always: NaN/Infinity become null (``allow_nan=False`` guards the rule). ``compact``: one line
    without spaces (journal lines, database columns); ``default`` as for ``json.dumps`` (other types)."""
    return json.dumps(_clean(doc), indent=None if compact else indent, allow_nan=False, default=default,
                      separators=(",", ":") if compact else None)


def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON (a value the data do not determine is written as null)")


class DuplicateKeyError(ValueError):
    """A JSON object names one key twice (``json`` keeps the last silently); the message names key and line."""


class _Dup(Exception):
    def __init__(self, key: str) -> None:
        self.key = key


def _no_duplicates(pairs: list) -> dict:
    out = {}
    for k, v in pairs:
        if k in out:
            raise _Dup(k)
        out[k] = v
    return out


def _duplicate_line(text: str, key: str) -> int:
    """Line of the second ``key`` in one object of ``text`` (valid JSON): a scan that tracks the open objects and
    skips strings with the decoder's own string reader."""
    from json.decoder import scanstring

    stack: list[set | None] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c == '"':
            value, end = scanstring(text, i + 1)
            j = end
            while j < n and text[j] in " \t\r\n":
                j += 1
            if j < n and text[j] == ":" and stack and stack[-1] is not None:
                if value == key and value in stack[-1]:
                    return text.count("\n", 0, i) + 1
                stack[-1].add(value)
            i = end
            continue
        if c == "{":
            stack.append(set())
        elif c == "[":
            stack.append(None)
        elif c in "}]":
            stack.pop()
        i += 1
    return 1


def loads_strict(text: str, name: str = "JSON"):
    """``json.loads`` for the station's inputs: NaN/Infinity refused, and a key given twice in one object refused
    with its line (``DuplicateKeyError``: ``NAME:LINE: key 'x' is given twice in one object``); JSON itself keeps
    the last value silently, and a calibration or map read that way is not the one its author checked."""
    try:
        return json.loads(text, parse_constant=_no_constant, object_pairs_hook=_no_duplicates)
    except _Dup as e:
        raise DuplicateKeyError(f"{name}:{_duplicate_line(text, e.key)}: key {e.key!r} is given twice in one object "
                                f"(JSON would keep the last one silently); give it once") from None


def read_json(path: str | Path, what: str = "JSON file"):
    """Parsed JSON of regular file ``path``; ``ConfigError`` in one line for anything else."""
    from station.robot.errors import ConfigError
    from station.yamlfile import decode, read_capped

    name = f"{what} {path}"
    text = decode(read_capped(path, ConfigError, name, MAX_JSON_BYTES), ConfigError, name)
    try:
        return loads_strict(text, name)
    except json.JSONDecodeError as e:
        raise ConfigError(f"{name}:{e.lineno}: not valid JSON ({e.msg})") from None
    except ValueError as e:
        raise ConfigError(f"{name}: {e}") from None
    except RecursionError:
        raise ConfigError(f"{name}: nested too deeply; not a station file") from None
