"""``station.report.mapsection``: the correction-map section of a report, from a session record: measurements
judged in mm/deg come back in SI, rows without values are left out, the calibration is named by file and hash."""

from __future__ import annotations

import math

import pytest

from station.report.mapsection import correction_map_section, payload_text


def _m(name, value, unit, high=None):
    return {"name": name, "value": value, "unit": unit, "low": None, "high": high}


def test_section_in_si_from_the_record():
    session = {
        "correction_map": {"file": "map.json", "payload": {"mass": 15.0, "com": [0.0, 0.0, 0.03]},
                           "map": {"mesh": {"type": "grid", "shape": [3, 3, 2]}, "samples": {"x": [[0]] * 40}},
                           "calibration": {"path": "/cells/a/result.json", "sha256": "ab" * 32, "model": "arm6",
                                           "parameters": {"offset.j2": {}, "compliance.j2": {}, "compliance.j3": {}},
                                           "payload": {"mass": 15.0, "com": [0, 0, 0.03]}}},
        "verdict": {"measurements": [_m("holdout_nominal_rms", 2.0, "mm"), _m("holdout_calibrated_rms", 0.2, "mm"),
                                     _m("holdout_rms", 0.05, "mm", high=0.1), _m("holdout_max", 0.12, "mm"),
                                     _m("holdout_rotation_rms", 0.01, "deg")]}}
    s = correction_map_section(session)
    assert s["mesh"] == "grid" and s["nodes"] == 18 and s["samples"] == 40 and s["file"] == "map.json"
    assert s["payload_text"] == "15 kg at [0, 0, 30] mm (tool frame)"
    cal = s["calibration"]
    assert cal["file"] == "result.json" and cal["sha256_short"] == "ab" * 6 and cal["parameters"] == 3
    assert cal["compliance"] == ["compliance.j2", "compliance.j3"]
    rows = {r["row"]: r for r in s["holdout"]}
    assert list(rows) == ["nominal model", "calibrated only", "calibrated + map"]
    assert rows["nominal model"]["rms_m"] == pytest.approx(2e-3)
    assert rows["calibrated + map"]["rotation_rms_rad"] == pytest.approx(math.radians(0.01))
    assert rows["calibrated + map"]["judged"] == ["holdout_rms"] and rows["calibrated only"]["max_m"] is None


def test_without_a_calibration_or_a_map():
    s = correction_map_section({"correction_map": {"map": {}}, "verdict": {"measurements": [
        _m("holdout_rms", 0.05, "mm"), _m("holdout_calibrated_rms", 0.2, "mm")]}})
    assert s["calibration"] is None and [r["row"] for r in s["holdout"]] == ["nominal + map"]
    assert correction_map_section({"verdict": {}}) is None
    assert payload_text({"mass": "x"}) is None
