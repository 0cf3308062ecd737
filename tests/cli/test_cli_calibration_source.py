"""``station.cli.calibration_source``: a calibration read from a result JSON, a report or a session (its journal
names the model), applied to the model: identified parameters take their estimate, the rest what was solved with."""

from __future__ import annotations

import json
import math
import re

import pytest

from station.cli.calibration_source import calibration_source
from station.kinematics import load_model
from station.robot.errors import ConfigError
from tests.records.test_records_cli import _write_journal


def _json(doc) -> str:
    """As the station writes JSON: a value the data do not determine (a point's nominal, NaN) is null."""
    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return None if isinstance(x, float) and math.isnan(x) else x
    return json.dumps(clean(doc))


def _expected(result: dict) -> dict[str, float]:
    return {n: (p["value"] if p["identifiable"] else p["nominal"]) for n, p in result["parameters"].items()
            if p["kind"] == "model"}


def test_a_result_file_applies_its_estimates(tmp_path, session_factory):
    session, _ = session_factory(seed=4)
    f = tmp_path / "r.json"
    f.write_text(_json(session["result"]))
    src = calibration_source(str(f))
    assert src.model == "ur5e" and src.what == str(f)
    model = src.apply(load_model("ur5e"))
    for name, value in _expected(session["result"]).items():
        assert model.param(name) == pytest.approx(value, abs=1e-15), name
    with pytest.raises(ConfigError, match="the calibration is for model 'ur5e', not 'ur10e'"):
        src.apply(load_model("ur10e"))


def test_a_report_and_a_session_give_the_same(tmp_path, session_factory):
    session, _ = session_factory(seed=5)
    folder = tmp_path / "sessions" / session["session"]
    _write_journal(folder, session)
    from_session = calibration_source(str(folder))
    assert from_session.what == f"session {session['session']}"
    rows = [{"name": n, **{k: p[k] for k in ("value", "nominal", "identifiable", "kind", "std", "unit")}}
            for n, p in session["result"]["parameters"].items()]
    report = tmp_path / "report.json"
    report.write_text(_json({"format": "station-report/1", "parameters": rows, "header": {"model": "ur5e"}}))
    from_report = calibration_source(str(report))
    assert from_report.values(load_model("ur5e")) == from_session.values(load_model("ur5e")) == pytest.approx(
        _expected(session["result"]))


@pytest.mark.parametrize("doc, needle", [
    ({"format": "station-report/1", "parameters": []}, "the report holds no solve result"),
    ({"format": "other/1"}, "expected a result (station-calibration/1"),
])
def test_what_is_not_a_calibration_is_one_line(tmp_path, doc, needle):
    f = tmp_path / "x.json"
    f.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match=re.escape(needle)) as e:
        calibration_source(str(f))
    assert "\n" not in str(e.value)
