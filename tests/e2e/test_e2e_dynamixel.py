"""End to end on Dynamixel (Protocol 2.0 emulator on a pty, real dynamixel_sdk): zero offsets recovered within
their uncertainty; ``station run`` killed with SIGKILL mid-procedure resumes without losing or repeating a
sample; a failing verdict exits 1 and is stored."""

import math
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from clirunner import station_proc, station_spawn
from station.mocks.launch import launch

from station.api import run as start
from station.cli.run_cmd import BUS_OPTIONS, demo_world
from station.engine import read_journal, session_from_journal
from station.records import open_records

TICK = 2 * math.pi / 4096  # XM430 position resolution (rad)


def _files(tmp_path, seed, time_mode="instant", time_scale=1.0):
    from station.mocks.world import World

    doc = demo_world("dynamixel", seed, time_mode)
    doc["motion"]["time_scale"] = time_scale
    world_path, cell_path = tmp_path / "world.yaml", tmp_path / "cell.yaml"
    world_path.write_text(yaml.safe_dump(doc))
    cell_path.write_text(yaml.safe_dump(World.from_file(world_path).station_cell()))
    return world_path, cell_path, f"DXL-{seed}"


@pytest.fixture
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    return tmp_path


def _check_offsets(record, hidden):
    """Identified offsets match the hidden truth within 4 sigma plus half an encoder count: a joint that hardly
    moves between poses (the waist) reads with the same rounding at every pose, a bias no spread reveals."""
    n = 0
    for name, p in record["result"]["parameters"].items():
        if name.startswith("offset.") and p["identifiable"]:
            assert abs(p["value"] - hidden[name]) <= 4 * p["std"] + TICK / 2, (name, p["value"], hidden[name], p["std"])
            n += 1
    return n


def test_zero_offsets_recovers_hidden_offsets(home):
    world_path, cell_path, serial = _files(home, seed=31)
    with launch("dynamixel", world_path, serial=serial) as emu:
        out = start("zero_offsets", emu.url, serial, cell=cell_path, options=dict(BUS_OPTIONS["dynamixel"]),
                    db=f"sqlite:///{home / 'r.db'}")
        hidden = emu.world.hidden()
    assert out.status == "completed" and out.passed, (out.error, out.record["verdict"])
    assert _check_offsets(out.record, hidden) == 4  # known socket position: all four zeros show
    assert (out.folder / "samples.csv").read_text().count("\n") == 2 + len(out.record["samples"])


def _journal_samples(home: Path) -> tuple[Path | None, int]:
    for j in (home / "home" / "sessions").glob("*/journal.jsonl"):
        return j, j.read_text().count('"type":"sample"')
    return None, 0


def test_kill_9_then_resume_keeps_every_sample(home):
    # realtime motion (4x): the run lasts long enough to be killed between samples
    world_path, cell_path, serial = _files(home, seed=32, time_mode="realtime", time_scale=4.0)
    db = f"sqlite:///{home / 'r.db'}"
    env = {**os.environ, "STATION_HOME": str(home / "home")}
    with launch("dynamixel", world_path, serial=serial) as emu:
        with station_spawn("run", "zero_offsets", "--robot", emu.url, "--serial", serial, "--cell", cell_path,
                           "--reference", "cell", "--cone", "70", "--db", db, "-q", env=env) as proc:
            end = time.monotonic() + 60
            n = 0
            while time.monotonic() < end and n < 6 and proc.running():
                journal, n = _journal_samples(home)
                time.sleep(0.01)
            assert proc.running() and n >= 6, proc.wait(timeout=5)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        _, before = read_journal(journal)
        kept = [e for e in before if e["type"] == "sample"]
        assert len(kept) >= 6 and not any(e["type"] == "end" for e in before)
        # resume in its own process too: the emulator thread keeps this one's interpreter to itself
        r = station_proc("resume", journal.parent.name, "-q", env=env, timeout=120)
        hidden = emu.world.hidden()
    assert r.code == 0 and r.out.strip().splitlines()[-1] == "PASS", r.err
    out = session_from_journal(journal)
    _, events = read_journal(journal)
    samples = [e for e in events if e["type"] == "sample"]
    poses = [e["pose"] for e in samples]
    assert len(poses) == len(set(poses)) == 24  # nothing repeated, nothing missing
    assert samples[:len(kept)] == kept  # what was recorded before the kill is untouched
    assert any(e["type"] == "resume" for e in events)
    assert _check_offsets(out, hidden) == 4
    with open_records(db) as rec:  # the db URL came from the journal header
        stored = rec.session(out["session"])
    assert len(stored["samples"]) == 24


def test_failing_verdict_exits_1_and_is_stored(home):
    world_path, cell_path, serial = _files(home, seed=33)
    strict = home / "strict.yaml"
    strict.write_text('format: station-limits/1\nversion: "test-strict"\nmodels:\n  omx:\n    zero_offsets:\n'
                      "      fit_rms: {high: 0.001, unit: mm}\n")
    db = f"sqlite:///{home / 'r.db'}"
    env = {**os.environ, "STATION_HOME": str(home / "home")}
    with launch("dynamixel", world_path, serial=serial) as emu:
        r = station_proc("run", "zero_offsets", "--robot", emu.url, "--serial", serial, "--cell", cell_path,
                         "--reference", "cell", "--cone", "70", "--db", db, "--limits", strict, "-q",
                         "--poses", "12", "--holdout", "2", env=env, timeout=120)
    assert r.code == 1, r.err
    assert r.out.strip().splitlines()[-1] == "FAIL"
    with open_records(db) as rec:
        (s,) = rec.sessions(serial)
        stored = rec.session(s["session"])
    assert stored["verdict"]["passed"] is False
    assert np.isfinite(stored["result"]["residuals"]["rms_after_m"])


def test_sigterm_stops_the_robot_and_journals_the_interruption(home):
    world_path, cell_path, serial = _files(home, seed=34, time_mode="realtime", time_scale=4.0)
    env = {**os.environ, "STATION_HOME": str(home / "home")}
    with launch("dynamixel", world_path, serial=serial) as emu:
        with station_spawn("run", "zero_offsets", "--robot", emu.url, "--serial", serial, "--cell", cell_path,
                           "--reference", "cell", "--cone", "70", "--db", f"sqlite:///{home / 'r.db'}", "-q",
                           env=env) as proc:
            end = time.monotonic() + 60
            n = 0
            while time.monotonic() < end and n < 3 and proc.running():
                journal, n = _journal_samples(home)
                time.sleep(0.01)
            if not proc.running():  # ended before it could be interrupted: say why
                pytest.fail(f"station exited {proc.returncode} before the interruption: {proc.wait().err}")
            assert n >= 3
            while not emu.world.is_moving() and time.monotonic() < end:  # interrupt it mid-motion
                time.sleep(0.002)
            proc.send_signal(signal.SIGTERM)
            r = proc.wait(timeout=30)
        assert r.code == 130, r.err
        assert "station resume" in r.err
        time.sleep(0.5)  # a controlled stop decelerates
        assert not emu.world.is_moving() and not emu.world.compliant
    _, events = read_journal(journal)
    assert events[-1]["type"] == "end" and events[-1]["status"] == "interrupted"
    assert any(e["type"] == "fault" and e["error"] == "Terminated" for e in events)


@pytest.mark.slow
def test_apply_releases_only_servos_friction_holds_then_parks_for_the_power_cycle(home, monkeypatch):
    """``zero_offsets --apply``, then a power cycle of the servos (EEPROM kept, RAM lost: torque off); the
    identification after it is the bus-conformance suite's (tests/e2e/test_bus_conformance.py). A DYNAMIXEL has no
    brake and its homing offset is EEPROM (written with the torque off): the write-back releases each servo
    alone, only where gravity's torque on its joint is below what the joint's friction holds (no collision, no
    joint moved); before the power is cut the arm is parked where no joint carries load (the servos' own Present
    Current says where), as a technician parks an arm without brakes."""
    world_path, cell_path, serial = _files(home, seed=35)
    db = f"sqlite:///{home / 'r.db'}"
    with launch("dynamixel", world_path, serial=serial) as emu:
        world = emu.world
        released: list[tuple[int, float, float]] = []
        moved: list[float] = []
        orig = type(world).set_enabled

        def set_enabled(w, on, joints=None):
            idx = list(range(w.n_joints)) if joints is None else [int(j) for j in np.atleast_1d(joints)]
            if not on:
                tau, fr = w.gravity_torque(), w.dynamics_friction()
                released.extend((j, float(tau[j]), float(fr[j])) for j in idx if w.enabled()[j])
                set_enabled.q = w.encoder_q().copy()
            elif getattr(set_enabled, "q", None) is not None:
                moved.append(float(np.max(np.abs(w.encoder_q() - set_enabled.q))))
                set_enabled.q = None
            return orig(w, on, joints)
        monkeypatch.setattr(type(world), "set_enabled", set_enabled)
        out = start("zero_offsets", emu.url, serial, cell=cell_path, options=dict(BUS_OPTIONS["dynamixel"]), db=db,
                    apply=True)
        assert out.status == "completed" and out.passed, (out.error, out.record["verdict"])
        wb = out.record["writeback"]
        assert wb["applied"] and wb["verified"]
        assert released and all(abs(tau) < fr for _, tau, fr in released), released
        assert moved and max(moved) <= TICK, moved  # no joint moved while a servo was released
        assert world.collisions == []
        monkeypatch.setattr(type(world), "set_enabled", orig)
        from station.robot import open_robot

        with open_robot(emu.url) as robot:  # the technician parks the arm, then switches the servos off and on
            while (q := robot.write_pose()) is not None:
                robot.move_joints(q)
            parked = world.encoder_q().copy()
        stored = [emu.emulator.devices[i].get("homing_offset") for i in emu.emulator.joint_ids]
        emu.emulator.power_cycle()
        assert np.max(np.abs(world.encoder_q() - parked)) <= TICK
        assert [emu.emulator.devices[i].get("homing_offset") for i in emu.emulator.joint_ids] == stored

