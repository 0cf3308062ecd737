"""``station.cli.map_cmd``: the output units of ``station map`` files and their column headers."""

from __future__ import annotations

import math

import pytest

from station.cli.map_cmd import _header, _units
from station.robot.errors import ConfigError


def test_output_units_and_headers():
    si = _units(None)
    assert si == (1.0, "", 1.0, "") and _header("x1", False, si) == "x1"  # SI: plain headers
    mm = _units("mm,deg")
    assert mm[0] == 1e-3 and mm[2] == pytest.approx(math.pi / 180)
    assert _header("x", False, mm) == "x[mm]" and _header("rx", True, mm) == "rx[deg]"
    with pytest.raises(ConfigError, match="--units 'furlong,deg': expected LENGTH,ANGLE"):
        _units("furlong,deg")
