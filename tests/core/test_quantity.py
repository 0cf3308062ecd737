"""``station.quantity``: option values with their unit (``--cone 50deg``, ``--max-std 1mm``, ``--tool 0,0,100mm``,
``--payload 0.5kg@0,0,30mm``), for the command line and the options procedures declare."""

from __future__ import annotations

import math

import pytest

from station.quantity import parse_option, parse_payload, parse_xyz
from station.robot.errors import ConfigError


def cone(text):
    return parse_option(text, "--cone", "angle", "deg", "50deg")


def max_std(text):
    return parse_option(text, "--max-std", "length", "m", "1mm")


def test_units_convert_to_the_bare_unit():
    assert cone("50") == 50.0 and cone(50) == 50.0  # a bare number keeps its documented unit
    assert cone("50deg") == pytest.approx(50.0, abs=1e-12)
    assert cone(f"{math.pi / 4}rad") == pytest.approx(45.0, abs=1e-12)
    assert max_std("1mm") == pytest.approx(1e-3, abs=1e-18)
    assert max_std("250um") == pytest.approx(2.5e-4, abs=1e-18)
    assert max_std("0.002") == 0.002


@pytest.mark.parametrize("text, needle", [
    ("1mm", "expected an angle, e.g. 50deg"),  # a length for an angle option
    ("fifty", "expected an angle with its unit"),
    ("50furlongs", "expected an angle with its unit"),
    ("nan", "not a finite number"),
])
def test_bad_values_are_one_line_naming_the_option(text, needle):
    with pytest.raises(ConfigError) as e:
        cone(text)
    msg = str(e.value)
    assert msg.startswith(f"--cone {text!r}: ") and needle in msg and "\n" not in msg


def test_points_and_payloads():
    assert parse_xyz("100,200,50mm", "--tool") == pytest.approx([0.1, 0.2, 0.05])
    assert parse_xyz("0.1, 0, -0.02", "--tool") == pytest.approx([0.1, 0.0, -0.02])  # bare: metres
    mass, com = parse_payload("250g")
    assert mass == pytest.approx(0.25) and com == (0.0, 0.0, 0.0)
    mass, com = parse_payload("0.5kg@0,0,30mm")
    assert mass == 0.5 and com == pytest.approx((0.0, 0.0, 0.03))
    for bad, needle in (("1,2", "expected x,y,z"), ("1,2,3in", "unknown length unit 'in'"),
                        ("1,2,1e999mm", "not a finite number")):
        with pytest.raises(ConfigError, match=needle):
            parse_xyz(bad, "--tool")
    with pytest.raises(ConfigError, match="expected a mass with its unit"):
        parse_payload("5")
