"""``station.report.isosection``: the ISO 9283 section of a report from a session's ``iso9283`` record: figures
per pose and model with their intervals, what is not a finite number left out, the judged model."""

from __future__ import annotations

import math

from station.report.isosection import iso9283_section


def test_poses_models_and_distance():
    iso = {"judged": "calibrated", "cycles": 30, "cube": {"edge": 0.2},
           "registration": {"nominal": {"rms_m": 3e-5}, "calibrated": {"rms_m": 2e-5}},
           "results": {
               "nominal": {"confidence": 0.95, "poses": {"P1": {"n": 30, "AP_p": 1.2e-3, "AP_p_ci": [1.1e-3, 1.3e-3],
                                                                "RP_l": 4e-5, "AP_a": math.nan}},
                           "distance": {"poses": ["P2", "P4"], "D_c": 0.3, "AD_p": 2e-4, "RD_p": 3e-5}},
               "calibrated": {"confidence": 0.95, "instrument": {"model": "LT"},
                              "poses": {"P1": {"n": 30, "AP_p": 5e-5, "AP_p_ci": [4e-5, 6e-5], "RP_l": 4e-5},
                                        "P2": {"n": 30, "AP_p": 6e-5, "AP_p_ci": ["nan", 1]}},
                              "distance": {"poses": ["P2", "P4"], "D_c": 0.3, "AD_p": 2e-5}}}}
    s = iso9283_section({"iso9283": iso})
    assert s["judged"] == "calibrated" and s["models"] == ["nominal", "calibrated"] and s["cycles"] == 30
    p1 = next(p for p in s["poses"] if p["pose"] == "P1")
    assert p1["n"] == 30 and p1["figures"]["nominal"]["AP_p"] == {"value": 1.2e-3, "ci": [1.1e-3, 1.3e-3],
                                                                   "unit": "m"}
    assert "AP_a" not in p1["figures"]["nominal"]  # NaN: not a figure
    p2 = next(p for p in s["poses"] if p["pose"] == "P2")
    assert p2["figures"]["nominal"] == {} and p2["figures"]["calibrated"]["AP_p"]["ci"] is None
    assert s["distance"]["pair"] == "P2-P4" and set(s["distance"]["figures"]["nominal"]) == {"AD_p", "RD_p"}
    assert s["instrument"] == {"model": "LT"} and s["registration"] == {"nominal": 3e-5, "calibrated": 2e-5}
    assert iso9283_section({}) is None
