"""``station.kinematics.tolerances``: a model file's manufacturing tolerances (prior standard deviations)."""

from __future__ import annotations

import math

import pytest

from station.kinematics.tolerances import parse_quantity, parse_tolerances, tolerances_to_doc


def test_quantities_in_si():
    assert parse_quantity("20um") == pytest.approx((2e-5, "length"))
    assert parse_quantity("20µm") == pytest.approx((2e-5, "length"))
    assert parse_quantity("0.3 mm")[0] == pytest.approx(3e-4)
    assert parse_quantity("0.5deg") == pytest.approx((math.radians(0.5), "angle"))
    for bad, needle in (("0.3", "expected a number with a unit"), ("3 parsecs", "unknown unit 'parsecs'"),
                        ("1e999mm", "not a finite number")):
        with pytest.raises(ValueError, match=needle):
            parse_quantity(bad)


def test_model_file_tolerances_and_back():
    # file in mm and deg: a bare number applies to lengths (mm) and angles (deg) alike
    tols = parse_tolerances({"offsets": "0.05deg", "dh": ["0.3mm", "0.1deg"], "tcp.z": 2}, "m.yaml",
                            1e-3, math.pi / 180)
    assert tols[0] == ("offsets", pytest.approx(math.radians(0.05)), "angle")
    assert tols[1] == ("dh", pytest.approx(3e-4), "length") and tols[2][2] == "angle"
    assert tols[3] == ("tcp.z", pytest.approx(2e-3), "length")
    assert tols[4] == ("tcp.z", pytest.approx(math.radians(2)), "angle")
    doc = tolerances_to_doc(tols[:3], "mm", "deg")
    assert doc == {"offsets": "0.05deg", "dh": ["0.3mm", "0.1deg"]}
    back = parse_tolerances(doc, "m.yaml", 1e-3, math.pi / 180)  # round trip
    assert [(s, q) for s, _, q in back] == [(s, q) for s, _, q in tols[:3]]
    assert [v for _, v, _ in back] == pytest.approx([v for _, v, _ in tols[:3]], rel=1e-12)
    assert parse_tolerances(None, "m.yaml", 1, 1) == ()


@pytest.mark.parametrize("doc, needle", [
    ([1, 2], "expected a mapping"),
    ({"dh": -1}, "tolerances.dh: a tolerance must be a positive number"),
    ({"dh": True}, "tolerances.dh: expected a number with a unit"),
    ({"dh": "-0.3mm"}, "tolerances.dh: a tolerance must be positive"),
    ({"dh": "0.3"}, "tolerances.dh: '0.3': expected a number with a unit"),
])
def test_bad_tolerances_name_the_file_and_field(doc, needle):
    with pytest.raises(ValueError, match=needle) as e:
        parse_tolerances(doc, "m.yaml", 1e-3, 1.0)
    assert str(e.value).startswith("m.yaml: ")
