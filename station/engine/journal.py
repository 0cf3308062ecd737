"""Append-only JSON-lines session journal: the one truth of a session (records and reports are projections).

Line 1 is the header (``type: header``, ``format: station-journal/2``); every later line is one event of the
schema in ``station.engine.events`` with a sequence number ``seq`` and the host time of the append ``t``.
Each append is checked against the schema, then flushed and fsynced before it returns, so an event that
``append`` returned for survives a crash or power loss. Reading validates every line against the schema
(``station-journal/1`` files are converted); a wrong line is one error naming the file, line and field
(``journal PATH:LINE: field q: ...``). A torn last line (power loss mid-write) is ignored on read and cut off
before the next append; a damaged line elsewhere is an error."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from station.engine import events as ev
from station.engine.events import FORMAT, FORMAT_V1, Event, Header, SchemaError


class JournalError(ValueError):
    """The journal file is missing, not a journal, or damaged before its last line."""


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


def _line(event: Event) -> bytes:
    return (json.dumps(event.to_dict(), separators=(",", ":")) + "\n").encode()


def make_header(header: Header | dict) -> Header:
    """The typed header of a new journal; a dict is checked field by field (one-line error naming it)."""
    try:
        if isinstance(header, Header):
            return ev.make(header)
        return ev.from_dict({"type": "header", **{k: v for k, v in header.items() if k != "format"}},
                            strict=False)
    except SchemaError as e:
        raise JournalError(f"journal header: {e}") from None


class Journal:
    """Open for appending. Use ``Journal.create`` for a new session, ``Journal.open`` to continue one."""

    def __init__(self, path: Path, header: Header, next_seq: int) -> None:
        self.path = Path(path)
        self.header = header
        self._seq = next_seq
        self._fh = open(self.path, "ab", buffering=0)  # noqa: SIM115 (kept open for the session)

    # ---- lifecycle -----------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, header: Header | dict) -> Journal:
        path = Path(path)
        if path.exists() and path.stat().st_size:
            raise JournalError(f"journal {path} already exists; use resume to continue it")
        head = make_header(header)
        head.seq, head.format = 0, FORMAT
        if head.t is None:
            head.t = time.time()
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            fh.write(_line(head))
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
        last = max((e.seq for e in events), default=0)
        return cls(path, header, last + 1)

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- writing -------------------------------------------------------------------------------
    def append(self, event: Event | dict) -> Event:
        """Check ``event`` against the schema, write it durably; returns it with ``seq`` and ``t`` (the append
        time) filled in."""
        try:
            e = ev.make(event)
        except SchemaError as err:
            kind = event.get("type") if isinstance(event, dict) else getattr(event, "type", "?")
            raise JournalError(f"journal {self.path}: {kind} event: {err}") from None
        e.seq, e.t = self._seq, time.time()
        self._fh.write(_line(e))
        os.fsync(self._fh.fileno())
        self._seq += 1
        return e

    def events(self) -> list[Event]:
        return read_journal(self.path)[1]


def _read(path: Path) -> tuple[Header, list[Event], int]:
    if not path.exists():
        raise JournalError(f"journal {path} does not exist")
    if not path.is_file():
        raise JournalError(f"journal {path} is not a file")
    data = path.read_bytes()
    lines = data.split(b"\n")
    events: list[Event] = []
    header: Header | None = None
    version = FORMAT
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
                raise ValueError("not a JSON object")
        except ValueError as e:
            if torn or (i == len(lines) - 2 and not lines[-1]):
                # a last line that does not parse was torn by power loss: drop it
                break
            raise JournalError(f"journal {path}:{i + 1}: damaged line ({e})") from None
        if torn:
            break  # parseable but no newline: the write may not have completed; treat as torn
        where = f"journal {path}:{i + 1}"
        if header is None:
            version = obj.get("format")
            if obj.get("type") != "header" or version not in (FORMAT, FORMAT_V1):
                raise JournalError(f"{where}: not a {FORMAT} (or /1) header")
        if version == FORMAT_V1:
            obj = ev.upgrade_v1(obj)
        try:
            event = ev.from_dict(obj)
        except SchemaError as e:
            raise JournalError(f"{where}: {e}") from None
        if header is None:
            header = event
        elif isinstance(event, Header):
            raise JournalError(f"{where}: a second header")
        else:
            events.append(event)
        pos = end
        good = end
    if header is None:
        raise JournalError(f"journal {path}: no header (empty or torn first line)")
    return header, events, good


def read_journal(path: str | Path) -> tuple[Header, list[Event]]:
    """``(header, events)``, typed and validated (a ``/1`` journal converted); a torn last line is ignored."""
    header, events, _ = _read(Path(path))
    return header, events
