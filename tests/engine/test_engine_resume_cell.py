"""A resumed session solves with the cell it started with: the known distances and planes travel in the journal
header with the points (they fix the length scale of a two-socket solve; without them a resumed session
would solve a different problem)."""

from __future__ import annotations

import yaml

from station.engine.journal import read_journal
from station.engine.runner import _cell_from_header, create_session
from station.kinematics import load_model
from station.robot.protocol import Identity


class _Robot:
    url = "paper://arm"

    def __init__(self) -> None:
        self.model = load_model("fr3")

    def identity(self) -> Identity:
        return Identity(vendor="paper", model="fr3", serial="SN-1", serial_source="url")


def test_distances_and_planes_survive_the_journal(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    cell = tmp_path / "cell.yaml"
    cell.write_text(yaml.safe_dump({
        "format": "station-cell/1", "units": {"length": "mm", "angle": "deg"},
        "points": [{"label": "A", "kind": "socket", "position": [500, -25, 100]},
                   {"label": "B", "kind": "socket", "position": [500, 25, 100]},
                   {"label": "P", "kind": "socket", "position": [400, 0, 100]}],
        "distances": [{"between": ["A", "B"], "distance": 50.002, "std": 0.001}],
        "planes": ["P"]}))
    s = create_session(_Robot(), "SN-1", name="script", cell=cell)
    header, _ = read_journal(s.journal.path)
    back = _cell_from_header(header.cell)
    ((a, b, d, std),) = back.distances
    assert (a, b) == ("A", "B") and abs(d - 0.050002) < 1e-15 and abs(std - 1e-6) < 1e-18
    assert back.planes == ["P"]
    assert set(back.points) == {"A", "B", "P"}
