"""``station.cli.compensate_cmd``: the targets file of ``station compensate`` (units from its header, SI inside)
and the ``--units`` option."""

from __future__ import annotations

import math

import numpy as np
import pytest

from station.cli.compensate_cmd import _units, read_targets
from station.robot.errors import ConfigError


def test_targets_in_mm_and_deg_are_read_in_si(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("name,x[mm],y[mm],z[mm],rx[deg],ry[deg],rz[deg]\nP1,450,-120.5,300,180,0,90\nP2,0.5,0,1,0,0,0\n")
    xyz, names, _ = read_targets(f)
    assert names == ["P1", "P2"]
    assert np.allclose(xyz[0], [0.45, -0.1205, 0.3, math.pi, 0, math.pi / 2])
    g = tmp_path / "p.csv"
    g.write_text("x[m],y[m],z[m]\n0.45,0,0.3\n")
    assert read_targets(g)[0].shape == (1, 3) and read_targets(g)[1] is None


@pytest.mark.parametrize("text, needle", [("x,y\n1,2\n", "missing column 'z'"),
                                          ("x,y,z,rx\n1,2,3,0\n", "missing column 'ry'"),
                                          ("x,y,z\n", "no data rows")])
def test_bad_targets_are_one_line_naming_the_file(tmp_path, text, needle):
    f = tmp_path / "t.csv"
    f.write_text(text)
    with pytest.raises(ConfigError, match=needle) as e:
        read_targets(f)
    assert str(f) in str(e.value) and "\n" not in str(e.value)


def test_units_option():
    assert _units(None) == (1.0, "m", 1.0, "rad") and _units("SI") == (1.0, "m", 1.0, "rad")
    k, length, a, angle = _units("mm,deg")
    assert (k, length, angle) == (1e-3, "mm", "deg") and a == pytest.approx(math.pi / 180)
    with pytest.raises(ConfigError, match="--units 'mm': expected LENGTH,ANGLE"):
        _units("mm")
