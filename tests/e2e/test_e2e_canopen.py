"""End to end on CANopen (CiA 402 drives on a python-can virtual channel, real canopen library): a drive fault
mid-procedure stops the robot and keeps the journal, a guarded approach, resume after a power loss in the
middle of the write-back. (zero_offsets --apply, power cycle and the identification after it run on every bus
in tests/e2e/test_bus_conformance.py.)"""

import pytest
from faultrig import demo_cell

from station.api import resume
from station.api import run as start
from station.engine import read_journal
from station.records import open_records


@pytest.fixture
def cell(tmp_path, monkeypatch):
    # not a heartbeat or SDO timing test: the drives run in this process (relaxed times, busrig.CANOPEN_RELAXED;
    # tests/drivers/canopen/test_canopen_faults.py and test_canopen_heartbeat.py cover the production times)
    with demo_cell("canopen", tmp_path, 21, relaxed=True) as c:
        monkeypatch.setenv("STATION_HOME", str(c.home))
        yield c.emu, c.cell_path, c.serial, c.db


def test_fault_mid_procedure_stops_robot_and_keeps_journal(cell):
    emu, cell_path, serial, db = cell
    world = emu.world
    seen = {"n": 0}

    def progress(done, total, text):
        if done == 5 and not seen["n"]:
            seen["n"] = 1
            world.faults.inject("device_fault", device=3)  # drive 3 (joint 3) reports a fault: EMCY

    out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, progress=progress)
    assert out.status == "error" and out.exit_code == 2
    assert not world.is_moving()
    header, events = read_journal(out.folder / "journal.jsonl")
    samples = [e for e in events if e["type"] == "sample"]
    assert len(samples) >= 5
    faults = [e for e in events if e["type"] == "fault"]
    assert faults and faults[0]["error"] in ("DeviceFault", "BusError", "SafetyStop", "TouchFailed")
    assert events[-1]["type"] == "end" and events[-1]["status"] == "error"
    with open_records(db) as rec:
        stored = rec.session(out.session)
    assert len(stored["samples"]) == len(samples)
    # after the fault is cleared the session resumes with the samples it has
    world.clear_fault()
    done = resume(out.session, db=db)
    if done.status == "completed":
        poses = [s["pose"] for s in done.record["samples"]]
        assert len(poses) == len(set(poses)) == 24
        assert [s["q"] for s in done.record["samples"][:len(samples)]] == [s["q"] for s in samples]
    else:  # a drive that latched its fault stays faulted until power-cycled: resume refuses, one line
        assert "\n" not in str(done.error)


def test_guarded_approach_stops_at_first_contact(tmp_path, monkeypatch, emulators):
    """A needle on the contact input (a 2 mm contact sphere): step down until the contact closes, bisect. Every
    sample is taken with the contact just closed: the true tip on the sphere's surface, to the bisection step.
    (Where on the sphere depends on the lateral aim error, so a contact sphere limits a TCP calibration to that
    error: the shipped 0.1 mm limits fail it, honestly.)"""
    import numpy as np
    import yaml
    from station.mocks.world import World

    from station.cli.run_cmd import demo_world
    from station.engine.touch import GuardedApproach

    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    doc = demo_world("canopen", 71)
    doc["robot"]["tool"] = {"x": 0.01, "y": 0.0, "z": 0.05, "rx": 0.0, "ry": 0.0, "rz": 0.0}
    doc["errors"] = {"explicit": {"tcp.x": 0.3e-3, "tcp.y": -0.2e-3, "tcp.z": 0.25e-3}}
    radius = 0.002
    doc["cell"] = {"contact_radius": radius, "points": [
        {"label": "N", "kind": "needle", "position": [0.40, 0.0, 0.70], "approach": [0, 0, 1]}]}
    world_path, cell_path = tmp_path / "w.yaml", tmp_path / "c.yaml"
    world_path.write_text(yaml.safe_dump(doc))
    cell_path.write_text(yaml.safe_dump(World.from_file(world_path).station_cell()))
    emu = emulators("canopen", world_path, serial="NEEDLE-1")
    out = start("tcp_4point", emu.url, "NEEDLE-1", cell=cell_path, touch=GuardedApproach(fine=0.01e-3),
                options={"n_fit": 6, "n_holdout": 1})
    world = emu.world
    assert out.status == "completed", out.error
    samples = out.record["samples"]
    assert len(samples) == 7 and all(x["status"]["touch"] for x in samples)
    tips = world.truth.position(np.array([x["q"] for x in samples]))
    dist = np.linalg.norm(tips - world.points["N"].position, axis=1)
    assert np.all(dist <= radius + 1e-9) and np.all(dist > radius - 0.03e-3)  # just inside: first contact


def test_resume_after_power_loss_in_the_middle_of_write_back(cell, tmp_path):
    """The journal ends right after the pre-image: the write may or may not have reached the drives. Resume
    reads what they hold and finishes the write-back either way, never writing on top of an unknown state."""
    import station

    emu, cell_path, serial, db = cell
    out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, apply=True,
                options={"n_fit": 12, "n_holdout": 2})
    assert out.status == "completed" and out.record["writeback"]["verified"], out.error
    before, after = out.record["writeback"]["before"], out.record["writeback"]["after"]
    lines = (out.folder / "journal.jsonl").read_bytes().splitlines(keepends=True)
    cut = next(i for i, ln in enumerate(lines) if b'"type":"writeback"' in ln and b'"phase":"pre-image"' in ln) + 1
    for variant in ("written", "not-written"):
        robot = station.connect(emu.url)
        robot.write_calibration(after if variant == "written" else before)
        robot.close()
        folder = tmp_path / "crash" / variant
        folder.mkdir(parents=True)
        (folder / "journal.jsonl").write_bytes(b"".join(lines[:cut]))  # same session: its record is updated
        done = resume(folder, db=db)
        assert done.status == "completed", done.error
        wb = done.record["writeback"]
        assert wb["applied"] and wb["verified"] and wb["before"] == before
        robot = station.connect(emu.url)
        held = robot.read_calibration()
        robot.close()
        assert all(abs(held[k] - after[k]) < 1e-6 for k in after)
        _, events = read_journal(folder / "journal.jsonl")
        assert sum(e["type"] == "sample" for e in events) == 14  # no sample retaken
