"""``station.mocks.world.cli``: warnings about a cell the arm cannot use, said when the world is written."""

from __future__ import annotations

import numpy as np
from station.mocks.world import World
from station.mocks.world.cli import cell_warnings


def test_an_unreachable_point_and_an_empty_cell_are_named():
    w = World.default(model="ur5e", seed=2)
    assert cell_warnings(w, "w.yaml") == []  # the built-in cell is reachable
    far = World.default(model="ur5e", seed=2, cell={"points": [{"label": "F", "kind": "socket",
                                                                "position": [3.0, 0.0, 0.05], "approach": [0, 0, 1]}]})
    (line,) = cell_warnings(far, "w.yaml")
    assert line.startswith("station: warning: w.yaml: cell.points F at [3000.0, 0.0, 50.0] mm") and "0%" in line
    assert np.allclose(far.points["F"].position, [3.0, 0.0, 0.05])
