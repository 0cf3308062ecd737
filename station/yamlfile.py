"""Read a YAML file with a one-line error naming the file (and the line when the YAML is malformed).

Shared by model, world, cell and limits files; pure apart from reading the file."""

from __future__ import annotations

from pathlib import Path

import yaml


def parse_yaml(text: str | bytes, error: type[Exception], name: str):
    """Parsed content of ``text`` (the bytes of file ``name``, e.g. kept for a checksum); ``error(message)``
    for bad YAML: ``NAME: line N not valid YAML (problem)``."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise error(f"{name}:{line} not valid YAML ({problem})") from None


def load_yaml(path: str | Path, error: type[Exception], what: str = "", hint: str = ""):
    """Parsed content of ``path``; ``error(message)`` is raised for an unreadable file or bad YAML.
    ``what`` prefixes the path (e.g. ``"cell file"``), ``hint`` is appended to a read error."""
    path = Path(path)
    name = f"{what} {path}" if what else str(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise error(f"{name}: cannot read ({e.strerror or e}){hint}") from None
    return parse_yaml(text, error, name)
