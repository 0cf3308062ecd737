"""Journal format versions: within ``station-journal/2`` a reader keeps the fields and event types it does not
know (a newer station of the same major version wrote them) and writes them back as they were, while every
field it knows is checked as strictly as before; a newer major version is refused in one line; a producer's
unknown field is still refused before anything is written."""

import json

import pytest

from station.engine import events as ev
from station.engine.journal import Journal, JournalError, read_journal
from station.engine.session_record import session_from_journal
from station.safeio import dumps_json

# what a newer station of the same major version might add: a field on the header, a sample, a step, a planned
# pose and the plan, a nested object, and a whole event type
EXTRA = {"header": {"site": {"line": 4, "cell": "C2"}}, "sample": {"temperature_c": 23.5},
         "step": {"operator_note": "re-seated"}, "plan": {"planner": "v9"}}


def _write_newer(tmp_path, minor: str = "2.7"):
    j = Journal.create(tmp_path / "s" / "journal.jsonl", {"session": "S1", "serial": "SN", "procedure": "p"})
    j.append(ev.Step(name="plan", status="start", info={"n": 2}))
    pose = {"index": 0, "point": "A", "q": [0.1, 0.2], "approach_q": [0.1, 0.25]}
    j.append(ev.Plan(plan={"poses": [pose], "settings": {}}))
    j.append(ev.Step(name="plan", status="done", duration=0.5))
    j.append(ev.Sample(point="A", q=[0.1, 0.2], pose=0, status={"touch": True}))
    j.append(ev.End(status="completed", n_samples=1))
    j.close()
    lines = [json.loads(x) for x in j.path.read_text().splitlines()]
    lines[0]["format"] = f"station-journal/{minor}"
    lines[0].update(EXTRA["header"])
    lines[1].update(EXTRA["step"])
    lines[2]["plan"].update(EXTRA["plan"])
    lines[2]["plan"]["poses"][0]["stiffness"] = [1.0, 2.0]
    lines[4].update(EXTRA["sample"])
    lines.insert(5, {"type": "thermal_drift", "seq": 99, "t": 1.0, "session": "S1", "dx": [1e-6, 0, 0]})
    text = "".join(dumps_json(x, compact=True) + "\n" for x in lines)
    j.path.write_text(text)
    return j.path, lines, text


def test_unknown_fields_of_the_same_major_version_are_kept_and_written_back_unchanged(tmp_path):
    path, lines, text = _write_newer(tmp_path)
    header, events = read_journal(path)
    assert header.format == "station-journal/2.7" and header.unknown == EXTRA["header"]
    assert events[0].unknown == EXTRA["step"] and events[0]["operator_note"] == "re-seated"
    assert events[1].plan["planner"] == "v9" and events[1].plan["poses"][0]["stiffness"] == [1.0, 2.0]
    sample = next(e for e in events if e.type == "sample")
    assert sample.unknown == EXTRA["sample"] and sample.q == [0.1, 0.2]  # the known fields as typed as ever
    assert next(e for e in events if e.type == "thermal_drift").data == {"dx": [1e-6, 0, 0]}
    # written back: byte for byte the lines that were read (the journal's own line writer)
    back = "".join(dumps_json(e.to_dict(), compact=True) + "\n" for e in [header, *events])
    assert back == text
    # a station that continues the journal (resume) leaves them as they are, and its own events read back too
    j = Journal.open(path)
    j.append(ev.Warn(message="resumed by an older minor version"))
    j.close()
    assert path.read_text().startswith(text)
    assert [e.to_dict() for e in read_journal(path)[1][:-1]] == lines[1:]
    # a copy made through the schema keeps them (make() of an event read from a journal)
    assert ev.make(sample).to_dict() == sample.to_dict()
    # the record keeps the sample as read (stored whole, so the records keep the field too)
    assert session_from_journal(path)["samples"][0]["temperature_c"] == 23.5


def test_known_fields_stay_strict_in_a_newer_minor_version(tmp_path):
    path, lines, _ = _write_newer(tmp_path)
    lines[4]["q"] = [0.1, "x"]
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    with pytest.raises(JournalError, match=r"journal\.jsonl:5: field q\[1\]: expected a number, got str"):
        read_journal(path)


def test_a_producer_with_an_unknown_field_is_refused_before_anything_is_written(tmp_path):
    j = Journal.create(tmp_path / "journal.jsonl", {"session": "S1", "serial": "SN", "procedure": "p"})
    size = j.path.stat().st_size
    with pytest.raises(JournalError, match="field tempreature_c: unknown field of a sample event"):
        j.append({"type": "sample", "point": "A", "q": [0.1], "tempreature_c": 23.5})
    j.close()
    assert j.path.stat().st_size == size


@pytest.mark.parametrize("fmt", ["station-journal/3", "station-journal/3.0", "station-journal/12.1"])
def test_a_newer_major_version_is_refused_in_one_line(tmp_path, fmt):
    from clirunner import station_main

    path, lines, _ = _write_newer(tmp_path)
    lines[0]["format"] = fmt
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    with pytest.raises(JournalError) as e:
        read_journal(path)
    msg = str(e.value)
    assert "\n" not in msg and f"{path}:1:" in msg and f"{fmt} is a newer major version" in msg
    assert "station-journal/2" in msg  # says what this station reads
    for argv in (["report", path], ["resume", path.parent]):  # the commands that read a journal
        code, _, err = station_main(*argv)
        assert code == 2 and err.strip().count("\n") == 0 and err.startswith("station: error: "), err
        assert "newer major version" in err


@pytest.mark.parametrize("fmt", ["station-journal/2.x", "station-journal/", "station-journal/1.5", "journal/2", 2])
def test_a_malformed_format_is_not_a_journal(tmp_path, fmt):
    path, lines, _ = _write_newer(tmp_path)
    lines[0]["format"] = fmt
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    with pytest.raises(JournalError, match=r":1: header field format: .* is not a station-journal/2"):
        read_journal(path)
