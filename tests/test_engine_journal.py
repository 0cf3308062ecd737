"""Session journal: durable appends, replay, torn last line (power loss), damaged lines, projection."""

import json
import math

import pytest

from station.engine.journal import Journal, JournalError, read_journal
from station.engine.session_record import session_from_journal


def _journal(tmp_path, **header):
    return Journal.create(tmp_path / "s" / "journal.jsonl", {"session": "S1", "serial": "SN", "procedure": "p",
                                                             **header})


def test_append_numbers_events_and_replays(tmp_path):
    j = _journal(tmp_path)
    a = j.append({"type": "step", "name": "connect", "status": "start"})
    b = j.append({"type": "sample", "point": "A", "q": [0.1, float("nan")], "pose": 0})
    j.close()
    assert (a["seq"], b["seq"]) == (1, 2)
    header, events = read_journal(j.path)
    assert header["format"] == "station-journal/1" and header["session"] == "S1"
    assert [e["seq"] for e in events] == [1, 2]
    assert events[1]["q"] == [0.1, None]  # JSON has no NaN: a missing value is null
    # continuing numbers after reopen
    j2 = Journal.open(j.path)
    assert j2.append({"type": "end", "status": "completed"})["seq"] == 3
    j2.close()


def test_torn_last_line_is_ignored_and_cut_before_next_append(tmp_path):
    j = _journal(tmp_path)
    j.append({"type": "sample", "point": "A", "q": [1.0], "pose": 0})
    j.close()
    with open(j.path, "ab") as fh:
        fh.write(b'{"type":"sample","point":"A","q":[2.0')  # power loss mid-write
    header, events = read_journal(j.path)
    assert [e["q"] for e in events] == [[1.0]]
    j2 = Journal.open(j.path)
    j2.append({"type": "sample", "point": "A", "q": [3.0], "pose": 1})
    j2.close()
    lines = j.path.read_text().splitlines()
    assert all(json.loads(x) for x in lines)  # no line is left broken
    assert [e["q"] for e in read_journal(j.path)[1]] == [[1.0], [3.0]]


def test_complete_but_unterminated_last_line_counts_as_torn(tmp_path):
    j = _journal(tmp_path)
    j.close()
    with open(j.path, "ab") as fh:
        fh.write(b'{"type":"sample","seq":1,"q":[1.0]}')  # no newline: the write did not complete
    assert read_journal(j.path)[1] == []


def test_damaged_middle_line_is_an_error_naming_the_line(tmp_path):
    j = _journal(tmp_path)
    j.append({"type": "step", "name": "a"})
    j.append({"type": "step", "name": "b"})
    j.close()
    lines = j.path.read_bytes().split(b"\n")
    lines[1] = b"{garbage"
    j.path.write_bytes(b"\n".join(lines))
    with pytest.raises(JournalError, match="line 2"):
        read_journal(j.path)


def test_not_a_journal(tmp_path):
    p = tmp_path / "x.jsonl"
    p.write_text('{"type": "sample"}\n')
    with pytest.raises(JournalError, match="header"):
        read_journal(p)
    with pytest.raises(JournalError, match="does not exist"):
        read_journal(tmp_path / "missing.jsonl")
    j = _journal(tmp_path)
    j.close()
    with pytest.raises(JournalError, match="already exists"):
        Journal.create(j.path, {"session": "again"})


def test_projection_to_session_record(tmp_path):
    j = _journal(tmp_path, model="ur5e", robot={"serial": "SN", "model": "ur5e"})
    s1 = j.append({"type": "sample", "point": "A", "q": [0.0], "pose": 0, "set": "fit"})
    j.append({"type": "sample", "point": "A", "q": [0.1], "pose": 1, "set": "fit"})
    j.append({"type": "discard", "sample": s1["seq"]})
    j.append({"type": "result", "result": {"model": "ur5e", "residuals": {}}})
    j.append({"type": "verdict", "passed": False, "measurements": [{"name": "fit_rms", "passed": False}]})
    j.append({"type": "writeback", "phase": "before", "before": {"offset.j1": 0.0}, "after": {"offset.j1": 0.1},
              "applied": False, "verified": False})
    j.append({"type": "writeback", "phase": "written", "applied": True})
    j.append({"type": "end", "status": "completed"})
    j.close()
    rec = session_from_journal(j.path.parent)
    assert rec["session"] == "S1" and rec["serial"] == "SN" and rec["model"] == "ur5e"
    assert [s["q"] for s in rec["samples"]] == [[0.1]]  # the discarded sample is gone
    assert rec["verdict"]["passed"] is False
    assert rec["writeback"]["before"] == {"offset.j1": 0.0} and rec["writeback"]["applied"] is True
    assert rec["finished"] is not None and rec["status"] == "completed"
    assert not math.isnan(len(rec["samples"]))
