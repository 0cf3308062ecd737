"""Append-only JSON-lines session journal: the one truth of a session (records and reports are projections).

Line 1 is the header (``type: header``, ``format: station-journal/1``); every later line is one event with a
sequence number ``seq`` and host time ``t``. Each append is flushed and fsynced before it returns, so an event
that ``append`` returned for survives a crash or power loss. A torn last line (power loss mid-write) is
ignored on read and cut off before the next append; a damaged line elsewhere is an error."""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

FORMAT = "station-journal/1"


class JournalError(ValueError):
    """The journal file is missing, not a journal, or damaged before its last line."""


def _clean(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays to Python; NaN/inf become null (JSON has no NaN: a value that
    does not exist, such as the position of a point the data could not see, is stored as null)."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy array or scalar
        return _clean(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class Journal:
    """Open for appending. Use ``Journal.create`` for a new session, ``Journal.open`` to continue one."""

    def __init__(self, path: Path, header: dict, next_seq: int) -> None:
        self.path = Path(path)
        self.header = header
        self._seq = next_seq
        self._fh = open(self.path, "ab", buffering=0)  # noqa: SIM115 (kept open for the session)

    # ---- lifecycle -----------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, header: dict) -> Journal:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists() and path.stat().st_size:
            raise JournalError(f"journal {path} already exists; use resume to continue it")
        head = _clean({"type": "header", "format": FORMAT, "seq": 0, "t": time.time(), **header})
        with open(path, "wb") as fh:
            fh.write((json.dumps(head, separators=(",", ":")) + "\n").encode())
            fh.flush()
            os.fsync(fh.fileno())
        _fsync_dir(path.parent)
        return cls(path, head, 1)

    @classmethod
    def open(cls, path: str | Path) -> Journal:
        path = Path(path)
        header, events, good_bytes = _read(path)
        if good_bytes < path.stat().st_size:  # cut a torn last line so the next event starts on its own line
            with open(path, "r+b") as fh:
                fh.truncate(good_bytes)
                fh.flush()
                os.fsync(fh.fileno())
        last = max((e.get("seq", 0) for e in events), default=0)
        return cls(path, header, last + 1)

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- writing -------------------------------------------------------------------------------
    def append(self, event: dict) -> dict:
        """Write one event durably; returns it with ``seq`` and ``t`` filled in."""
        if "type" not in event:
            raise JournalError("journal: an event needs a 'type'")
        ev = _clean({**event, "seq": self._seq, "t": event.get("t", time.time())})
        line = (json.dumps(ev, separators=(",", ":")) + "\n").encode()
        self._fh.write(line)
        os.fsync(self._fh.fileno())
        self._seq += 1
        return ev

    def events(self) -> list[dict]:
        return read_journal(self.path)[1]


def _read(path: Path) -> tuple[dict, list[dict], int]:
    if not path.exists():
        raise JournalError(f"journal {path} does not exist")
    data = path.read_bytes()
    lines = data.split(b"\n")
    events: list[dict] = []
    header: dict | None = None
    good = 0
    pos = 0
    for i, raw in enumerate(lines):
        end = pos + len(raw) + 1
        last = i == len(lines) - 1
        if not raw.strip():
            pos = end
            if not last:
                good = end
            continue
        torn = last  # the final piece has no newline: it was cut mid-write
        try:
            obj = json.loads(raw)
            if not isinstance(obj, dict):
                raise ValueError("not an object")
        except ValueError as e:
            if torn or (i == len(lines) - 2 and not lines[-1]):
                # a last line that does not parse was torn by power loss: drop it
                break
            raise JournalError(f"journal {path}: line {i + 1} is damaged ({e})") from None
        if torn:
            break  # parseable but no newline: the write may not have completed; treat as torn
        if header is None:
            if obj.get("type") != "header" or obj.get("format") != FORMAT:
                raise JournalError(f"journal {path}: line 1 is not a {FORMAT} header")
            header = obj
        else:
            events.append(obj)
        pos = end
        good = end
    if header is None:
        raise JournalError(f"journal {path}: no header (empty or torn first line)")
    return header, events, good


def read_journal(path: str | Path) -> tuple[dict, list[dict]]:
    """``(header, events)``; a torn last line is ignored."""
    header, events, _ = _read(Path(path))
    return header, events
