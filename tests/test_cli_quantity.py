"""``station.cli.quantity``: option values with their unit (``--cone 50deg``, ``--max-std 1mm``)."""

from __future__ import annotations

import math

import pytest

from station.cli.quantity import parse_option
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
