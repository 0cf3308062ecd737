"""Read a YAML file with a one-line error naming the file (and the line when the YAML is malformed).

Shared by model files, world files and cell files; pure apart from reading the file."""

from __future__ import annotations

from pathlib import Path

import yaml


def load_yaml(path: str | Path, error: type[Exception], what: str = "", hint: str = ""):
    """Parsed content of ``path``; ``error(message)`` is raised for an unreadable file or bad YAML.
    ``what`` prefixes the path (e.g. ``"cell file"``), ``hint`` is appended to a read error."""
    path = Path(path)
    name = f"{what} {path}" if what else str(path)
    try:
        return yaml.safe_load(path.read_text())
    except OSError as e:
        raise error(f"{name}: cannot read ({e.strerror or e}){hint}") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        raise error(f"{name}:{line} not valid YAML") from None
