"""``station.performance.cube``: the ISO 9283 test cube's poses as the standard places them (clause 6.2: P1 at the
centre of a diagonal plane, P2..P5 on its diagonals at 10 % of the diagonal's length from the corners), checked
geometrically for every plane."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from station.performance.cube import PLANES, TestCube

CENTRE = np.array([0.4, -0.1, 0.3])
EDGE = 0.2


@pytest.mark.parametrize("plane", PLANES)
def test_test_positions_lie_on_a_diagonal_plane_at_ten_percent(plane):
    cube = TestCube(CENTRE, EDGE, np.eye(3), plane)
    p = cube.test_positions()
    assert np.allclose(p["P1"], CENTRE)
    corners = cube.corners()
    diag = EDGE * np.sqrt(3)  # the plane's diagonal: the cube's space diagonal
    pts = np.array([p[f"P{k}"] for k in range(2, 6)])
    # each P2..P5 is 10 % of the diagonal from one cube corner, towards the centre
    for x in pts:
        d = np.linalg.norm(corners - x, axis=1)
        assert d.min() == pytest.approx(0.1 * diag, rel=1e-12)
        assert np.linalg.norm(x - CENTRE) == pytest.approx(0.4 * diag, rel=1e-12)
    assert np.allclose(pts[0] + pts[2], 2 * CENTRE) and np.allclose(pts[1] + pts[3], 2 * CENTRE)  # opposite pairs
    # all five lie in one plane through the centre that contains two opposite cube edges
    normal = np.cross(pts[0] - CENTRE, pts[1] - CENTRE)
    assert np.allclose((pts - CENTRE) @ normal, 0, atol=1e-15)
    on_plane = [c for c in corners if abs((c - CENTRE) @ normal) < 1e-12]
    assert len(on_plane) == 4
    axis = "xyz".index(plane[0])  # the edges in the plane run along the plane's named axis
    assert sum(np.allclose(np.delete(a - b, axis), 0) for a, b in itertools.combinations(on_plane, 2)) == 2


def test_probe_points_registration_and_round_trip():
    cube = TestCube(CENTRE, EDGE, np.eye(3), "z-", ["given"])
    probes = cube.probe_positions()
    assert len(probes) == 27 and np.allclose(probes.mean(axis=0), CENTRE)
    assert np.allclose(np.abs(probes - CENTRE).max(axis=0), EDGE / 2)
    reg = cube.registration_positions()
    assert len(reg) == 8 and all(np.allclose(np.abs(v - CENTRE), 0.8 * EDGE / 2) for v in reg.values())
    T = cube.pose(CENTRE, "+z")
    assert np.allclose(T[:3, 3], CENTRE + [0, 0, 0.01])
    back = TestCube.from_dict(cube.to_dict())
    assert back.plane == "z-" and back.edge == EDGE and np.allclose(back.centre, CENTRE) and back.notes == ["given"]
