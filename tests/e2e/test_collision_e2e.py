"""End to end on the emulated UR5e of `station demo` (real ur_rtde client on loopback), with a world that knows
the table as truth and stops the arm on any contact (``cell.collision: stop``, a UR protective stop over the
wire): the calibration completes, so no link touched the table; a station that is told nothing about the
table (``mounting: none``) plans the elbow through it and is stopped by the world, so the first result is not
an accident of the test."""

import numpy as np
import pytest
import yaml
from station.mocks.launch import launch

from station.api import run as start
from station.cli.run_cmd import demo_world
from station.engine import read_journal
from station.kinematics.collision import Checker


def _run(tmp_path, monkeypatch, station_cell_edit=None):
    from station.mocks.world import World

    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    doc = demo_world("ur", seed=5)
    doc["cell"] = {"collision": "stop"}  # the demo cell points, the default table plane, stop on contact
    world_path, cell_path = tmp_path / "world.yaml", tmp_path / "cell.yaml"
    world_path.write_text(yaml.safe_dump(doc))
    world = World.from_file(world_path)  # the same truth the emulator process serves
    cell = world.station_cell()
    if station_cell_edit:
        station_cell_edit(cell)
    cell_path.write_text(yaml.safe_dump(cell))
    serial = doc["buses"]["ur"]["serial"]
    with launch("ur", world_path, serial=serial) as emu:
        out = start("zero_offsets", emu.url, serial, cell=cell_path, db=f"sqlite:///{tmp_path / 'r.db'}")
    return world, out


def test_the_ur5e_demo_calibrates_without_touching_the_table(tmp_path, monkeypatch):
    world, out = _run(tmp_path, monkeypatch)
    # the emulator's world stops the arm (a UR protective stop) at the first contact of any link with the table
    assert out.status == "completed" and out.passed, (out.error, out.record.get("verdict"))
    # the poses the station recorded, checked on the TRUE robot (hidden offsets) against the true table
    _, events = read_journal(out.folder / "journal.jsonl")
    q = np.array([e["q"] for e in events if e.get("type") == "sample"])
    assert len(q) == 28
    assert all(h is None for h in Checker(world.truth, world.spec.keep_out).hits(q))
    plan = next(e["plan"] for e in events if e.get("type") == "plan")
    assert plan["settings"]["keep_out"]["mounting"]["name"] == "mounting plane"


@pytest.mark.slow
def test_a_station_told_nothing_about_the_table_is_stopped_by_the_world(tmp_path, monkeypatch):
    def ignore_the_table(cell):
        cell["mounting"] = "none"

    world, out = _run(tmp_path, monkeypatch, ignore_the_table)
    assert out.status != "completed" and out.exit_code == 2
    assert "protective stop" in str(out.error).lower(), out.error
    # what the world stopped: the station's plan, replayed on the truth, puts a link into the table
    _, events = read_journal(out.folder / "journal.jsonl")
    plan = next(e["plan"] for e in events if e.get("type") == "plan")
    q = np.array([p["approach_q"] for p in plan["poses"]])
    hits = [h for h in Checker(world.truth, world.spec.keep_out).hits(q) if h is not None]
    assert hits and hits[0].obstacle == "mounting plane"
