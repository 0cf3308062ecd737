"""End to end on CANopen (CiA 402 drives on a python-can virtual channel, real canopen library): zero offsets
recovered within their uncertainty, write-back (homing on the current position, stored) verified by a held-out
check and, after a power cycle of the drives, by a verify run whose identified offsets are within 3 sigma of
zero; a drive fault mid-procedure stops the robot and keeps the journal."""

import time

import pytest
from station.mocks.launch import launch

from station.api import resume
from station.api import run as start
from station.cli.run_cmd import BUS_OPTIONS, write_demo_files
from station.engine import read_journal
from station.records import open_records


@pytest.fixture
def cell(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world_path, cell_path, serial = write_demo_files("canopen", tmp_path, seed=21, time_mode="instant")
    with launch("canopen", world_path, serial=serial) as emu:
        # not a heartbeat test: the emulator runs in this process, so at load ~9 on 2 cores its heartbeat thread
        # waits for the GIL/CPU behind the solver and the station's threads (2009 ms gaps measured); the consumer
        # time is the documented URL option heartbeat_timeout_ms (production default 800 ms is unchanged;
        # tests/test_canopen_faults.py covers heartbeat loss)
        # SDO answers too (sdo_timeout_ms), and the drives' consumer of the station's heartbeat, a thread of this
        # process (master_timeout_ms; tests/test_canopen_heartbeat.py covers a lost station)
        emu.url += "&heartbeat_timeout_ms=5000&sdo_timeout_ms=2000&master_timeout_ms=5000"
        yield emu, cell_path, serial, f"sqlite:///{tmp_path / 'records.db'}"


def _check_offsets(record, hidden, k=4.0):
    """Every identified offset matches the world's hidden truth within k standard deviations."""
    got = 0
    for name, p in record["result"]["parameters"].items():
        if name.startswith("offset.") and p["identifiable"]:
            assert abs(p["value"] - hidden[name]) <= k * p["std"], (name, p["value"], hidden[name], p["std"])
            got += 1
    return got


def test_zero_offsets_apply_then_verify(cell):
    emu, cell_path, serial, db = cell
    hidden = emu.world.hidden()
    before = start("verify", emu.url, serial, cell=cell_path, db=db)
    assert before.status == "completed" and before.passed is False and before.exit_code == 1  # zeros are off
    out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, apply=True,
                options=dict(BUS_OPTIONS["canopen"]))
    assert out.status == "completed", out.error
    assert out.passed and out.exit_code == 0 and out.stored and out.report.exists()
    assert _check_offsets(out.record, hidden) == 4  # j1 (socket unknown) and j6 (tip on its axis) are unseen
    wb = out.record["writeback"]
    assert wb["applied"] and wb["verified"]
    assert all(abs(wb["after"][n] - wb["before"][n] - (p["value"] - p["nominal"])) < 1e-6
               for n, p in out.record["result"]["parameters"].items() if n.startswith("offset.") and p["identifiable"])
    # the drives' power cycle: what was stored (the zero each homing set) is kept, the rest is lost (the
    # station's PDO layout, heartbeat settings): the calibration must hold across it
    emu.emulator.power_cycle()
    time.sleep(0.05)
    assert all(d.get(0x1017) == 0 for d in emu.emulator.drives.values())  # volatile settings are gone
    after = start("verify", emu.url, serial, cell=cell_path, db=db)
    assert after.passed, (after.status, after.error, after.record.get("verdict"))
    # the offsets the verify run's own touches identify (the station's solver on its samples): zero within 3 sigma
    import numpy as np

    from station.kinematics import load_model
    from station.solver import Observations, solve

    samples = after.record["samples"]
    obs = Observations(np.array([x["q"] for x in samples]), np.array([x["point"] for x in samples]), None)
    res = solve(load_model("arm6"), obs, identify="offsets", reference="unknown")
    got = 0
    for name, p in res.parameters.items():
        if name.startswith("offset.") and p.identifiable:
            assert abs(p.value - p.nominal) <= 3 * p.std, (name, p.value, p.nominal, p.std)
            got += 1
    assert got >= 3
    with open_records(db) as rec:
        ids = {s["session"] for s in rec.sessions(serial)}
    assert {before.session, out.session, after.session} <= ids


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


def test_guarded_approach_stops_at_first_contact(tmp_path, monkeypatch):
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
    with launch("canopen", world_path, serial="NEEDLE-1") as emu:
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
