"""``station.kinematics.modelformat``: what every model file reader shares: the units a model file may state and
the one number rule (finite, and written as a number)."""

from __future__ import annotations

import math

import pytest

from station.kinematics.modelformat import ANGLE, FORMAT, LENGTH, ModelFileError, number


def test_units_and_format():
    assert FORMAT == "station-model/1"
    assert LENGTH == {"m": 1.0, "mm": 1e-3} and pytest.approx({"rad": 1.0, "deg": math.pi / 180}) == ANGLE


@pytest.mark.parametrize("value, expect", [(1, 1.0), (2.5, 2.5), (-0.0, 0.0)])
def test_numbers(value, expect):
    assert number(value, "m.yaml: joints[1].d") == expect


@pytest.mark.parametrize("value, needle", [(True, "expected a number, got True"), ("1_0", "expected a number"),
                                           ("1", "expected a number, got '1'"), (None, "expected a number"),
                                           (float("inf"), "not a finite number"), (float("nan"), "not a finite")])
def test_what_is_not_a_number_names_the_field(value, needle):
    with pytest.raises(ModelFileError, match=needle) as e:
        number(value, "m.yaml: joints[1].d")
    assert str(e.value).startswith("m.yaml: joints[1].d: ")
