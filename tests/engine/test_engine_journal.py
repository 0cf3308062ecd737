"""Session journal: durable appends, replay, torn last line (power loss), damaged lines, the event schema
(validated on write and on read, one line naming file:line and field), station-journal/1 read and converted,
projection to the session record."""

import dataclasses
import json
import math
import re

import pytest

from station.engine import events as ev
from station.engine.journal import Journal, JournalError, read_journal
from station.engine.session_record import session_from_journal


def _journal(tmp_path, **header):
    return Journal.create(tmp_path / "s" / "journal.jsonl", {"session": "S1", "serial": "SN", "procedure": "p",
                                                             **header})


def test_append_numbers_events_and_replays(tmp_path):
    j = _journal(tmp_path)
    a = j.append(ev.Step(name="connect", status="start"))
    b = j.append({"type": "result", "result": {"points": {"A": [0.1, float("nan")]}}})
    j.close()
    assert (a.seq, b.seq) == (1, 2) and a.t is not None and b.t >= a.t
    header, events = read_journal(j.path)
    assert header.format == "station-journal/2" and header.session == "S1" and header.units.startswith("SI")
    assert [e.seq for e in events] == [1, 2]
    assert isinstance(events[0], ev.Step) and isinstance(events[1], ev.Result)
    assert events[1].result["points"]["A"] == [0.1, None]  # JSON has no NaN: a missing value is null
    # continuing numbers after reopen
    j2 = Journal.open(j.path)
    assert j2.append(ev.End(status="completed")).seq == 3
    j2.close()


def test_every_line_carries_every_field_of_its_type(tmp_path):
    j = _journal(tmp_path)
    j.append(ev.Sample(point="A", q=[0.1, 0.2], t_read=12.5, pose=0))
    j.close()
    line = json.loads(j.path.read_text().splitlines()[1])
    assert line["type"] == "sample" and line["t_read"] == 12.5 and line["t"] > 1e9  # reading time vs append time
    assert set(line) == {"type"} | {f.name for f in dataclasses.fields(ev.Sample)}


def test_producer_errors_are_refused_before_writing(tmp_path):
    j = _journal(tmp_path)
    size = j.path.stat().st_size
    for bad, field in [({"type": "sample", "point": "A", "q": [0.1, float("nan")]}, "q[1]"),
                       ({"type": "sample", "point": "A", "q": [0.1], "t_reed": 1.0}, "t_reed"),
                       ({"type": "step", "name": "x", "status": "begun"}, "status"),
                       ({"type": "writeback", "phase": "stage"}, "phase"),
                       ({"type": "fault", "message": "m"}, "error"),
                       ({"name": "no type"}, "type")]:
        with pytest.raises(JournalError, match=re.escape(f"field {field}:")):
            j.append(bad)
    assert j.path.stat().st_size == size  # nothing written
    j.close()


def test_custom_events_of_scripts_are_kept(tmp_path):
    j = _journal(tmp_path)
    e = j.append({"type": "socket_distance", "value_m": 0.25, "note": "mine"})
    j.close()
    _, events = read_journal(j.path)
    assert isinstance(events[0], ev.Custom) and events[0].type == "socket_distance"
    assert events[0]["value_m"] == 0.25 and events[0].seq == e.seq


def test_torn_last_line_is_ignored_and_cut_before_next_append(tmp_path):
    j = _journal(tmp_path)
    j.append(ev.Sample(point="A", q=[1.0], pose=0))
    j.close()
    with open(j.path, "ab") as fh:
        fh.write(b'{"type":"sample","point":"A","q":[2.0')  # power loss mid-write
    header, events = read_journal(j.path)
    assert [e.q for e in events] == [[1.0]]
    j2 = Journal.open(j.path)
    j2.append(ev.Sample(point="A", q=[3.0], pose=1))
    j2.close()
    lines = j.path.read_text().splitlines()
    assert all(json.loads(x) for x in lines)  # no line is left broken
    assert [e.q for e in read_journal(j.path)[1]] == [[1.0], [3.0]]


def test_complete_but_unterminated_last_line_counts_as_torn(tmp_path):
    j = _journal(tmp_path)
    j.close()
    with open(j.path, "ab") as fh:
        fh.write(b'{"type":"sample","seq":1,"t":1.0,"point":"A","q":[1.0]}')  # no newline: write did not complete
    assert read_journal(j.path)[1] == []


def test_damaged_middle_line_is_an_error_naming_the_line(tmp_path):
    j = _journal(tmp_path)
    j.append(ev.Step(name="a", status="start"))
    j.append(ev.Step(name="b", status="start"))
    j.close()
    lines = j.path.read_bytes().split(b"\n")
    lines[1] = b"{garbage"
    j.path.write_bytes(b"\n".join(lines))
    with pytest.raises(JournalError, match=r"journal .*journal.jsonl:2: damaged line"):
        read_journal(j.path)


@pytest.mark.parametrize("field,value,expect", [
    ("q", "0.1,0.2", r":2: field q: expected a list, got str"),
    ("q", [0.1, "x"], r":2: field q\[1\]: expected a number, got str"),
    ("pose", True, r":2: field pose: expected an integer, got bool"),
    ("set", "train", r":2: field set: 'train' is not one of fit, holdout"),
    ("seq", None, r":2: field seq: expected an integer, got null"),
])
def test_wrong_field_on_read_is_one_line_naming_file_line_and_field(tmp_path, field, value, expect):
    j = _journal(tmp_path)
    j.append(ev.Sample(point="A", q=[0.1, 0.2], pose=0))
    j.append(ev.End(status="completed"))
    j.close()
    lines = j.path.read_text().splitlines()
    d = json.loads(lines[1])
    d[field] = value
    lines[1] = json.dumps(d)
    j.path.write_text("\n".join(lines) + "\n")
    with pytest.raises(JournalError, match=expect) as e:
        read_journal(j.path)
    assert "\n" not in str(e.value) and str(j.path) in str(e.value)


def test_missing_required_field_on_read(tmp_path):
    j = _journal(tmp_path)
    j.append(ev.Fault(step="solve", error="X", message="m"))
    j.close()
    lines = j.path.read_text().splitlines()
    d = json.loads(lines[1])
    del d["message"]
    lines[1] = json.dumps(d)
    j.path.write_text("\n".join(lines) + "\n")
    with pytest.raises(JournalError, match=r":2: field message: missing from a fault event"):
        read_journal(j.path)


@pytest.mark.parametrize("text, needle", [
    ('{"type": "sample"}\n', "x.jsonl:1: not a station-journal/2"),
    ('{"type": "header", "format": "station-journal/9", "seq": 0}\n', "header"),
    (None, "does not exist"),
])
def test_not_a_journal(tmp_path, text, needle):
    p = tmp_path / "x.jsonl"
    if text is not None:
        p.write_text(text)
    with pytest.raises(JournalError, match=needle):
        read_journal(p)


def test_create_refuses_an_existing_journal_and_a_bad_header(tmp_path):
    j = _journal(tmp_path)
    j.close()
    with pytest.raises(JournalError, match="already exists"):
        Journal.create(j.path, {"session": "again"})
    with pytest.raises(JournalError, match="field serial"):
        Journal.create(tmp_path / "t" / "journal.jsonl", {"session": "S2", "procedure": "p"})


def test_projection_to_session_record(tmp_path):
    j = _journal(tmp_path, model="ur5e", robot={"serial": "SN", "model": "ur5e"})
    s1 = j.append(ev.Sample(point="A", q=[0.0], pose=0, t_read=100.0))
    j.append(ev.Sample(point="A", q=[0.1], pose=1, t_read=101.0))
    j.append(ev.Discard(sample=s1.seq))
    j.append(ev.Result(result={"model": "ur5e", "residuals": {}}))
    j.append(ev.Verdict(passed=False, measurements=[{"name": "fit_rms", "passed": False}]))
    j.append(ev.Writeback(phase="pre-image", before={"offset.j1": 0.0}, after={"offset.j1": 0.1}))
    j.append(ev.Writeback(phase="written", after={"offset.j1": 0.1}, readback={"offset.j1": 0.1}, applied=True))
    j.append(ev.End(status="completed"))
    j.close()
    rec = session_from_journal(j.path.parent)
    assert rec["session"] == "S1" and rec["serial"] == "SN" and rec["model"] == "ur5e"
    assert [s["q"] for s in rec["samples"]] == [[0.1]]  # the discarded sample is gone
    assert rec["samples"][0]["t_read"] == 101.0 and rec["samples"][0]["t"] > 1e9
    assert rec["verdict"]["passed"] is False
    wb = rec["writeback"]
    assert wb["before"] == {"offset.j1": 0.0} and wb["applied"] is True and wb["verified"] is False
    assert wb["phase"] == "written" and wb["readback"] == {"offset.j1": 0.1}
    assert rec["finished"] is not None and rec["status"] == "completed"
    assert not math.isnan(len(rec["samples"]))


# ---- station-journal/1, as the engine and the jog UI wrote it before the schema ----------------------------
V1_ENGINE = [
    {"type": "header", "format": "station-journal/1", "seq": 0, "t": 1700000000.0, "session": "E1",
     "procedure": "zero_offsets", "procedure_path": "/x/zero_offsets.py", "procedure_sha256": "ab",
     "procedure_title": "Zero offsets", "serial": "SN1", "operator": "op", "station": "host1", "url": "ur://h",
     "model": "ur5e", "robot": {"serial": "SN1", "model": "ur5e"}, "limits": {"path": "l", "version": "1",
                                                                                "sha256": "cd"},
     "cell": None, "options": {"apply": True}, "db": None, "versions": {"python": "3.11"}},
    {"type": "step", "name": "solve", "status": "start", "identify": "offsets", "session": "E1", "seq": 1,
     "t": 1700000001.0},
    {"type": "sample", "point": "A", "q": [0.1, 0.2], "raw": [1, 2], "raw_unit": "count", "t_read": 1700000001.5,
     "t_device": None, "measured": None, "pose": 0, "set": "fit", "status": {"touch": True}, "session": "E1",
     "seq": 2, "t": 1700000002.0},
    {"type": "writeback", "phase": "before", "before": {"offset.j1": 0.0}, "after": {"offset.j1": 0.01},
     "applied": False, "verified": False, "session": "E1", "seq": 3, "t": 1700000003.0},
    {"type": "writeback", "phase": "written", "after": {"offset.j1": 0.01}, "readback": {"offset.j1": 0.01},
     "applied": True, "session": "E1", "seq": 4, "t": 1700000004.0},
    {"type": "writeback", "phase": "verified", "verified": True, "check": {"passed": True}, "session": "E1",
     "seq": 5, "t": 1700000005.0},
    {"type": "end", "status": "completed", "passed": True, "session": "E1", "seq": 6, "t": 1700000006.0},
]
V1_JOG = [
    {"type": "header", "format": "station-journal/1", "seq": 0, "t": 1700000000.0, "procedure": "jog",
     "procedure_sha256": None, "mode": "technician",
     "station": {"host": "bench", "robot_url": "dynamixel:///dev/pts/3", "identify": "offsets,tcp",
                 "reference": "unknown"},
     "robot": {"vendor": "ROBOTIS", "model": "omx", "serial": "J1", "firmware": "", "url": ""}, "model": "omx",
     "serial": "J1", "operator": "tech", "versions": {"station": "0.1.0"}, "started": "2023-11-14T22:13:20+00:00",
     "units": "SI (m, rad)", "t_created": 1700000000.0, "session": "jog-J1"},
    {"type": "sample", "point": "A", "q": [0.1], "raw": [2048], "raw_unit": "tick", "t": 1700000010.25,
     "t_device": None, "measured": None, "pose": 0, "set": "fit", "status": {"touch": True}, "session": "jog-J1",
     "seq": 1},
    {"type": "step", "name": "enable", "status": "ok", "session": "jog-J1", "seq": 2, "t": 1700000011.0},
    {"type": "writeback", "stage": "pre-image", "before": {"offset.j1": 0.0}, "after": {"offset.j1": 0.02},
     "applied": False, "verified": False, "note": "technician write-back", "session": "jog-J1", "seq": 3,
     "t": 1700000012.0},
    {"type": "writeback", "stage": "done", "before": {"offset.j1": 0.0}, "after": {"offset.j1": 0.02},
     "readback": {"offset.j1": 0.02}, "applied": True, "verified": True, "note": "technician write-back",
     "session": "jog-J1", "seq": 4, "t": 1700000013.0},
    {"type": "end", "status": "completed", "n_samples": 1, "session": "jog-J1", "seq": 5, "t": 1700000014.0},
]


def _write(path, objs):
    path.write_text("".join(json.dumps(o) + "\n" for o in objs))
    return path


def test_v1_engine_journal_reads_as_v2(tmp_path):
    header, events = read_journal(_write(tmp_path / "e.jsonl", V1_ENGINE))
    assert header.format == "station-journal/2" and header.mode == "procedure" and header.station == "host1"
    step, sample = events[0], events[1]
    assert step.info == {"identify": "offsets"}
    assert sample.t_read == 1700000001.5 and sample.t == 1700000002.0
    assert [e.phase for e in events if isinstance(e, ev.Writeback)] == ["pre-image", "written", "verified"]
    rec = session_from_journal(tmp_path / "e.jsonl")
    assert rec["writeback"]["applied"] is True and rec["writeback"]["verified"] is True


def test_v1_jog_journal_reads_as_v2_with_one_meaning_per_field(tmp_path):
    header, events = read_journal(_write(tmp_path / "j.jsonl", V1_JOG))
    assert header.station == "bench" and header.url == "dynamixel:///dev/pts/3" and header.mode == "technician"
    assert header.options == {"identify": "offsets,tcp", "reference": "unknown"}
    sample = events[0]
    assert sample.t_read == 1700000010.25  # the jog UI wrote the reading time as t
    assert events[1].status == "done"
    wb = [e for e in events if isinstance(e, ev.Writeback)]
    assert [e.phase for e in wb] == ["pre-image", "written"]
    assert wb[-1].applied is True and wb[-1].verified is False  # /1's "verified" was only the read-back
    rec = session_from_journal(tmp_path / "j.jsonl")
    assert rec["writeback"]["applied"] is True and rec["writeback"]["verified"] is False
    # a /1 journal is continued in its own file with /2 lines
    j = Journal.open(tmp_path / "j.jsonl")
    j.append(ev.Sample(point="B", q=[0.2], t_read=5.0))
    j.close()
    assert read_journal(tmp_path / "j.jsonl")[1][-1].point == "B"


def test_v1_damaged_field_is_named_too(tmp_path):
    bad = [dict(o) for o in V1_ENGINE]
    bad[2] = {**bad[2], "q": [0.1, "zero"]}
    with pytest.raises(JournalError, match=r"e.jsonl:3: field q\[1\]: expected a number"):
        read_journal(_write(tmp_path / "e.jsonl", bad))
