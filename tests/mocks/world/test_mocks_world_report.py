"""``station.mocks.world.report``: ``station mock world show``'s account of the hidden truth, checked against the
world's own parameters in the units asked for."""

from __future__ import annotations

import math

from station.mocks.world import World
from station.mocks.world.report import truth_report


def _row(text: str, name: str) -> list[str]:
    return next(line.split() for line in text.splitlines() if line.strip().startswith(name + " "))


def test_hidden_errors_in_mm_and_deg_and_in_si():
    w = World.default(model="ur5e", seed=3, errors={"explicit": {"offset.j2": 0.002, "dh.j2.a": 0.0005}})
    text = truth_report(w)
    name, nominal, true, diff, unit = _row(text, "offset.j2")
    assert unit == "deg" and float(diff) == round(math.degrees(0.002), 6)
    assert abs(float(true) - float(nominal) - float(diff)) < 2e-6
    name, nominal, true, diff, unit = _row(text, "dh.j2.a")
    assert unit == "mm" and float(diff) == 0.5 and float(nominal) == round(w.nominal.param("dh.j2.a") * 1e3, 6)
    si = truth_report(w, "m", "rad")
    assert float(_row(si, "offset.j2")[3]) == 0.002 and _row(si, "dh.j2.a")[4] == "m"
    assert f"hidden errors ({len(w.errors())} parameters" in text and "seed 3" in text
    for label, p in w.points.items():  # every cell point with its true position in mm
        row = _row(text, label)
        assert [float(x) for x in row[2:5]] == [round(v * 1e3, 4) for v in p.position]
