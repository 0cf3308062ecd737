"""``station.textfile``: strict reading of text files (regular file, size cap, UTF-8 only) and the line of a field."""

from __future__ import annotations

import os

import pytest

from station.textfile import YamlDoc, decode, dotted, read_capped


class Bad(Exception):
    pass


def test_dotted_paths_and_the_line_of_the_nearest_located_ancestor():
    assert dotted(("joints", 2, "encoder", "gear")) == "joints[2].encoder.gear"
    assert dotted(()) == ""
    doc = YamlDoc("m.yaml", {}, {("joints",): 3, ("joints", 2): 7})
    assert doc.line(("joints", 2, "encoder")) == 7  # not located itself: its item's line
    assert doc.where(("joints", 2, "encoder")) == "m.yaml:7: joints[2].encoder"
    assert doc.where(("units",)) == "m.yaml: units"  # no line known
    assert doc.where() == "m.yaml"


def test_decode_names_the_line_of_the_first_byte_that_is_not_text():
    assert decode("a: 1\nb: é\n".encode(), Bad, "f.yaml") == "a: 1\nb: é\n"
    assert decode(b"\xef\xbb\xbfa: 1\n", Bad, "f.yaml") == "a: 1\n"  # the UTF-8 BOM is dropped
    with pytest.raises(Bad, match=r"^f.yaml:3: not UTF-8 text \(byte 0xe9\)"):
        decode(b"a: 1\nb: 2\nc: caf\xe9\n", Bad, "f.yaml")  # latin-1 on line 3
    with pytest.raises(Bad, match=r"^f.yaml:2: binary data \(control character U\+0000\)"):
        decode(b"a: 1\nb\x00\n", Bad, "f.yaml")
    with pytest.raises(Bad, match="UTF-16"):
        decode("a: 1\n".encode("utf-16"), Bad, "f.yaml")


def test_read_capped_refuses_what_is_not_a_small_regular_file(tmp_path):
    f = tmp_path / "small.txt"
    f.write_bytes(b"x" * 100)
    assert read_capped(f, Bad, "small.txt", limit=100) == b"x" * 100
    with pytest.raises(Bad, match="larger than 0 KiB"):
        read_capped(f, Bad, "small.txt", limit=99)
    with pytest.raises(Bad, match="is a directory"):
        read_capped(tmp_path, Bad, "dir")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(Bad, match="is a FIFO"):  # refused without blocking on a reader
        read_capped(fifo, Bad, "fifo")
    with pytest.raises(Bad, match="is a device"):
        read_capped("/dev/zero", Bad, "zero")
    with pytest.raises(Bad, match=r"cannot read \(No such file or directory\), hint"):
        read_capped(tmp_path / "absent", Bad, "absent", hint=", hint")
