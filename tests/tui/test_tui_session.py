"""The jog UI's session (an engine session in technician mode): journal events (fsynced) and a samples.csv that
the `station solve` reader accepts, kept equal to the journal's live samples."""

from __future__ import annotations

import numpy as np
import pytest

from station.engine.journal import read_journal
from station.engine.session_record import session_from_journal
from station.kinematics import load_model
from station.robot import JointSnapshot
from station.robot.errors import ConfigError
from station.samplesfile import read_samples
from station.tui.controller import parse_reference
from station.tui.session import session_header, technician_session


def _session(tmp_path, model):
    header = session_header(identity={"vendor": "test", "model": model.name, "serial": "SN7", "firmware": "",
                                      "url": ""},
                            model_name=model.name, serial="SN7", identify="offsets", reference="unknown",
                            url="test://")
    # the session journals what the UI reads from the robot; no robot is needed to test the folder
    return technician_session(None, header, folder=tmp_path / "s", model=model)


def test_parse_reference_units_and_labels():
    assert parse_reference(None) == "unknown"
    assert parse_reference(["unknown"]) == "unknown"
    a = parse_reference("0.1,0.2,0.05")["A"]
    b = parse_reference("100,200,50mm")["A"]
    np.testing.assert_allclose(a, [0.1, 0.2, 0.05])
    np.testing.assert_allclose(a, b)
    ref = parse_reference(["A=0,0,1", "B=10,20,30 mm"])
    np.testing.assert_allclose(ref["B"], [0.01, 0.02, 0.03])
    for bad in ("1,2", "1,2,nan", "1,2,3furlong", "x,y,z"):
        with pytest.raises(ConfigError, match="--reference"):
            parse_reference(bad)


def test_samples_journaled_and_csv_readable(tmp_path):
    model = load_model("scara")  # has a prismatic joint: metres in the csv
    s = _session(tmp_path, model)
    rng = np.random.default_rng(1)
    qs = [rng.uniform(model.lower / 2, model.upper / 2) for _ in range(3)]
    kept = [s.add_sample(JointSnapshot(q, tuple(range(model.n_joints)), "count", 1.0 + i), "AB"[i % 2], pose=i,
                         status={"touch": True}) for i, q in enumerate(qs)]
    # each sample is in the journal as soon as add_sample returned
    _, events = read_journal(s.folder / "journal.jsonl")
    assert [e["seq"] for e in events if e["type"] == "sample"] == [k.seq for k in kept]
    s.discard(kept[1], reason="technician")
    _, events = read_journal(s.folder / "journal.jsonl")
    assert events[-1].type == "discard" and events[-1].sample == kept[1].seq
    assert all(e.session == s.id for e in events)
    record = session_from_journal(s.folder)
    assert [e["seq"] for e in record["samples"]] == [kept[0].seq, kept[2].seq]
    samples = read_samples(s.samples_csv, model.joints)
    np.testing.assert_array_equal(samples.q, np.array([qs[0], qs[2]]))
    assert list(samples.point) == ["A", "A"]
    s.end()
    header, events = read_journal(s.folder / "journal.jsonl")
    assert header.procedure == "jog" and header.serial == "SN7" and header.mode == "technician"
    assert header.options == {"identify": "offsets", "reference": "unknown"} and header.url == "test://"
    # the reading time the UI gave is the sample's t_read; t is when it was journaled
    assert [e.t_read for e in events if e.type == "sample"] == [1.0, 2.0, 3.0]
    assert events[-1]["type"] == "end"


def test_refuses_existing_journal(tmp_path):
    model = load_model("omx")
    _session(tmp_path, model).end()
    with pytest.raises(ConfigError, match="already has a journal"):
        _session(tmp_path, model)
