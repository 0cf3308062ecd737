"""The report's correction-map section (station/report/mapsection.py): a map on the nominal model shows no
calibration and no calibrated-only row; a session without a map has no section. The map on a calibration, from a
real session: tests/procedures/test_correction_map_payload.py."""

from __future__ import annotations

import copy
import json
import re

import pytest

from station.report import write_report


@pytest.fixture(scope="module")
def session(session_factory):
    return session_factory(seed=11)[0]


def _measure(name, value, unit="mm", quantity="length", high=None):
    return {"name": name, "value": value, "unit": unit, "quantity": quantity, "low": None, "high": high,
            "marginal": False, "passed": True}


def test_no_map_no_section(session, tmp_path):
    html = write_report(session, tmp_path).read_text()
    assert "Correction map" not in html and json.loads((tmp_path / "report.json").read_text())["correction_map"] is None


def test_map_on_the_nominal_model(session, tmp_path):
    s = copy.deepcopy(session)
    s["correction_map"] = {"file": "map.json", "calibration": None, "payload": None,
                           "map": {"mesh": {"type": "simplex", "shape": [2, 2, 2, 2, 2, 2]},
                                   "samples": {"x": [[0.0] * 6] * 64}}}
    s["verdict"]["measurements"] += [_measure("holdout_nominal_rms", 0.2719), _measure("holdout_rms", 0.0401, high=0.1),
                                     _measure("holdout_max", 0.0635, high=0.25),
                                     _measure("holdout_rotation_rms", 0.0228, "deg", "angle")]
    html = write_report(s, tmp_path).read_text()
    rep = json.loads((tmp_path / "report.json").read_text())["correction_map"]
    assert rep["calibration"] is None and rep["nodes"] == 64 and rep["samples"] == 64
    rows = {r["row"]: r for r in rep["holdout"]}
    assert list(rows) == ["nominal model", "nominal + map"]
    assert rows["nominal + map"]["rms_m"] == pytest.approx(0.0401e-3) and rows["nominal + map"]["judged"] == [
        "holdout_rms", "holdout_max"]
    assert rows["nominal + map"]["rotation_rms_rad"] == pytest.approx(0.0228 * 3.141592653589793 / 180)
    section = html[html.index("<h2>Correction map</h2>"):html.index("<h2>Pose coverage</h2>")]
    assert "the nominal model (no parametric calibration)" in section and "calibrated only" not in section
    assert "simplex mesh, 64 nodes, 64 samples" in section
    row = re.search(r"<tr><td>nominal \+ map.*?</tr>", section).group(0)
    assert re.findall(r'<td class="n">([^<]*)</td>', row) == ["0.0401", "0.0635", "0.0228"]
