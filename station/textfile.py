"""Text files read strictly (a regular file, at most a size, UTF-8 text only) and the shape of a parsed one with
the line of every field. No yaml here: ``station.yamlfile`` parses YAML with these, the samples reader reads CSV
with them, and a built-in model whose parse is cached (``station.kinematics.catalog``) needs no yaml at all."""

from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

MAX_BYTES = 4 * 1024 * 1024  # a model/world/cell/limits file is a few kB; 4 MiB is generous


@dataclass
class YamlDoc:
    """A parsed YAML file: ``data`` (plain dicts, lists, str, int, float, bool, None) and the line of every
    key and item by path (``("joints", 2, "encoder")``)."""

    name: str
    data: object
    lines: dict[tuple, int] = field(default_factory=dict)

    def line(self, path) -> int | None:
        """Line of ``path`` or of its nearest located ancestor."""
        path = tuple(path)
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return None

    def where(self, path=()) -> str:
        """``NAME:LINE: FIELD`` for an error message (``NAME: FIELD`` when the line is unknown)."""
        line = self.line(path)
        head = f"{self.name}:{line}" if line else self.name
        return f"{head}: {dotted(path)}" if path else head


def dotted(path) -> str:
    """``("joints", 2, "encoder", "gear")`` -> ``joints[2].encoder.gear``."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def decode(data: bytes, error: type[Exception], name: str) -> str:
    """UTF-8 text of ``data`` or ``error`` naming the line of the first byte that is not text."""
    if data[:2] in (b"\xff\xfe", b"\xfe\xff") or data[:4] in (b"\x00\x00\xfe\xff", b"\xff\xfe\x00\x00"):
        raise error(f"{name}:1: the file is UTF-16/UTF-32 text; save it as UTF-8")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise error(f"{name}:{line}: not UTF-8 text (byte 0x{data[e.start]:02x}); save the file as UTF-8") from None
    bad = re.search(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f\ufffe\uffff]", text)
    if bad:
        line = text[:bad.start()].count("\n") + 1
        raise error(f"{name}:{line}: binary data (control character U+{ord(bad.group()):04X}); not a text file")
    return text


def read_capped(path: str | Path, error: type[Exception], name: str, limit: int = MAX_BYTES, hint: str = "") -> bytes:
    """The bytes of regular file ``path`` (at most ``limit``), or ``error`` in one line: a FIFO, device or
    directory is refused before anything is read from it (reading ``/dev/zero`` or a FIFO would never end)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError as e:
        raise error(f"{name}: cannot read ({e.strerror or e}){hint}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                    else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
            raise error(f"{name}: is {kind}, not a regular file; refused{hint}")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(limit + 1)
    except OSError as e:
        raise error(f"{name}: cannot read ({e.strerror or e}){hint}") from None
    finally:
        os.close(fd)
    if len(data) > limit:
        raise error(f"{name}: larger than {limit // 1024} KiB; refused (is it the right file?)")
    return data
