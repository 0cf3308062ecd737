"""Append-only JSON-lines session journal: the one truth of a session (records and reports are projections).

Line 1 is the header (``type: header``, ``format: station-journal/2``); every later line is one event of the
schema in ``station.engine.events`` with a sequence number ``seq`` and the host time of the append ``t``. A
journal of the same major version written by a newer station (``station-journal/2.N``, fields this station
does not know) is read with those fields kept; a newer major version is refused in one line.
Each append is checked against the schema, then flushed and fsynced before it returns, so an event that
``append`` returned for survives a crash or power loss. Reading validates every line against the schema
(``station-journal/1`` files are converted); a wrong line is one error naming the file, line and field
(``journal PATH:LINE: field q: ...``). A torn last line (power loss mid-write) is reported (``torn``), kept in
``journal.jsonl.torn`` and cut off before the next append; a damaged line elsewhere is an error.

An append that cannot complete (short write, ENOSPC, EROFS, EIO) raises :class:`JournalWriteError` after cutting
the partial line off again, so the journal stays valid and the next event starts on its own line; the journal
remembers it (``lost``), and a session with a lost event can never end in PASS. Free space is checked with
:func:`check_space` before a run and before each motion (``$STATION_MIN_FREE_MB``, default 16 MiB)."""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

from station.engine import events as ev
from station.engine.events import FORMAT, FORMAT_V1, Event, Header, SchemaError
from station.safeio import dumps_json, loads_strict

MIN_FREE_DEFAULT = 16 * 1024 * 1024  # bytes kept free for the journal: ~10^4 events of a busy session


class JournalError(ValueError):
    """The journal file is missing, not a journal, or damaged before its last line."""


class JournalWriteError(JournalError):
    """An event could not be written durably (disk full, read-only, I/O error); the journal was left valid.
    (A ValueError like every journal error, so journal readers stay free of the robot package; the runner
    turns it into the station's one-line error.)"""


def min_free() -> int:
    """Bytes that must stay free on the journal's file system (``$STATION_MIN_FREE_MB``)."""
    text = os.environ.get("STATION_MIN_FREE_MB")
    if not text:
        return MIN_FREE_DEFAULT
    try:
        return int(float(text) * 1024 * 1024)
    except ValueError:
        raise JournalWriteError(f"$STATION_MIN_FREE_MB={text!r} is not a number of MiB") from None


def check_space(folder: str | Path, what: str = "") -> int:
    """Free bytes on ``folder``'s file system; :class:`JournalWriteError` when fewer than :func:`min_free`
    (said before anything moves, instead of a journal that cannot take the next sample)."""
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    need = min_free()
    if free < need:
        raise JournalWriteError(f"only {free / 2**20:.1f} MiB free on {folder} (the journal needs "
                                f"{need / 2**20:.0f} MiB, $STATION_MIN_FREE_MB){'; ' + what if what else ''}")
    return free


def check_writable(folder: str | Path) -> None:
    """``folder`` can hold a journal: it exists (created if not) and a file can be created, written, fsynced
    there. One line naming the folder otherwise (e.g. a read-only ``$STATION_HOME/sessions``)."""
    folder = Path(folder)
    probe = folder / f".station-write-check-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            if os.write(fd, b"x") != 1:
                raise OSError(28, "short write")
            os.fsync(fd)
        finally:
            os.close(fd)
            probe.unlink(missing_ok=True)
    except OSError as e:
        raise JournalWriteError(f"cannot write session journals in {folder}: {e.strerror or e}") from None


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
    # strict JSON: events are already checked (a NaN in a nullable field is null, in a required one refused);
    # dumps_json keeps a NaN that slipped through from ever reaching the file
    return (dumps_json(event.to_dict(), compact=True) + "\n").encode()


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
        self.lost: list[str] = []  # events that could not be written (the session can never PASS)
        self.torn: str | None = None  # what a torn last line held when the journal was opened (reported)

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
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "wb") as fh:
                fh.write(_line(head))
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as e:
            with contextlib.suppress(OSError):
                path.unlink()  # a header that is not whole is no journal
            raise JournalWriteError(f"journal {path}: could not write the header ({e.strerror or e})") from None
        _fsync_dir(path.parent)
        return cls(path, head, 1)

    @classmethod
    def open(cls, path: str | Path) -> Journal:
        """Continue a journal. A torn last line is cut so the next event starts on its own line; its bytes are
        kept in ``journal.jsonl.torn`` and described in ``journal.torn`` (the caller reports it)."""
        path = Path(path)
        header, events, good_bytes = _read(path)
        size = path.stat().st_size
        torn = None
        if good_bytes < size:
            with open(path, "r+b") as fh:
                fh.seek(good_bytes)
                cut = fh.read()
                if cut.strip():
                    keep = path.with_name(path.name + ".torn")
                    with open(keep, "ab") as k:
                        k.write(cut + (b"" if cut.endswith(b"\n") else b"\n"))
                        k.flush()
                        os.fsync(k.fileno())
                    line = data_lines(path, good_bytes)
                    torn = (f"journal {path}:{line}: damaged last line ({len(cut)} bytes, not a complete event) "
                            f"cut off; kept in {keep.name}")
                fh.truncate(good_bytes)
                fh.flush()
                os.fsync(fh.fileno())
        last = max((e.seq for e in events), default=0)
        j = cls(path, header, last + 1)
        j.torn = torn
        return j

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
        self._write(_line(e), e.type)
        self._seq += 1
        return e

    def _write(self, data: bytes, kind: str) -> None:
        """All of ``data`` on disk (fsynced), or nothing: a short write or an OS error cuts the file back to
        where it was and raises :class:`JournalWriteError` (one line, naming the journal and the cause)."""
        fd = self._fh.fileno()
        start = os.fstat(fd).st_size
        done = 0
        try:
            while done < len(data):
                n = os.write(fd, data[done:])
                if n <= 0:
                    raise OSError(28, "short write (no space left on device?)")
                done += n
            os.fsync(fd)
            return
        except OSError as err:
            cause = err.strerror or str(err)
        try:
            os.ftruncate(fd, start)
            os.fsync(fd)
        except OSError as err:
            cause += f"; the partial line could not be cut off ({err.strerror or err})"
        self.lost.append(kind)
        raise JournalWriteError(f"journal {self.path}: could not write the {kind} event ({cause}); the robot is "
                                f"stopped, the journal is kept up to event {self._seq - 1}")

    def events(self) -> list[Event]:
        return read_journal(self.path)[1]


def data_lines(path: Path, upto: int) -> int:
    """The 1-based number of the line that starts at byte ``upto``."""
    with open(path, "rb") as fh:
        return fh.read(upto).count(b"\n") + 1


def _line_object(raw: bytes, path: Path, i: int, torn: bool) -> dict | None:
    """Line ``i`` as a JSON object; None for a last line that does not parse (torn by power loss: dropped)."""
    try:
        obj = loads_strict(raw, "line")
        if not isinstance(obj, dict):
            raise ValueError("not a JSON object")
    except ValueError as e:
        if torn:
            return None
        raise JournalError(f"journal {path}:{i + 1}: damaged line ({e})") from None
    return obj


def _header_version(obj: dict, where: str) -> str:
    """The format of the journal whose first line is ``obj`` (the current one, or /1 read by conversion)."""
    if obj.get("type") != "header":
        raise JournalError(f"{where}: not a {FORMAT} (or /1) header")
    try:
        return FORMAT_V1 if ev.check_format(obj.get("format")) == 1 else FORMAT
    except SchemaError as e:
        raise JournalError(f"{where}: header {e}") from None


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
        # a last piece without a newline was cut mid-write: dropped even when it parses (it may be incomplete)
        obj = _line_object(raw, path, i, torn=last or (i == len(lines) - 2 and not lines[-1]))
        if obj is None or last:
            break
        where = f"journal {path}:{i + 1}"
        if header is None:
            version = _header_version(obj, where)
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
    """``(header, events)``, typed and validated (a ``/1`` journal converted); a torn last line is not an event
    (:func:`torn_tail` says whether there is one)."""
    header, events, _ = _read(Path(path))
    return header, events


def torn_tail(path: str | Path) -> str | None:
    """A one-line description of a damaged last line of the journal at ``path``, None when it ends cleanly."""
    path = Path(path)
    _, _, good = _read(path)
    size = path.stat().st_size
    if good >= size:
        return None
    with open(path, "rb") as fh:
        fh.seek(good)
        if not fh.read().strip():
            return None
    return f"journal {path}:{data_lines(path, good)}: damaged last line ({size - good} bytes, not a complete event)"
