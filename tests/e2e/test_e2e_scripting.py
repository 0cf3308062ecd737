"""The scripted API end to end (CANopen emulator, real canopen library): the docs/scripting.md flow, a
technician's manual touch through the ManualTouch provider, and teardown when a script raises."""

import numpy as np
import pytest
from clirunner import station_proc
from faultrig import demo_cell

import station
from station.engine import ManualTouch, read_journal


@pytest.fixture
def cell(tmp_path, monkeypatch):
    # not a heartbeat or SDO timing test: the drives run in this process (relaxed times, busrig.CANOPEN_RELAXED;
    # tests/drivers/canopen/test_canopen_faults.py and test_canopen_heartbeat.py cover the production times)
    with demo_cell("canopen", tmp_path, 61, relaxed=True) as c:
        monkeypatch.setenv("STATION_HOME", str(c.home))
        yield c.emu, c.cell_path, c.serial, c.db


def test_scripted_session_like_the_docs(cell):
    emu, cell_path, serial, db = cell
    robot = station.connect(emu.url)
    assert robot.identity().serial == serial
    with station.session(robot, serial, cell=cell_path, options={"n_fit": 12, "n_holdout": 2}, db=db) as s:
        plan = s.plan(s.points("socket"), identify="offsets")
        for pose in s.todo(plan):
            s.approach(pose)
            s.seat(pose)
            s.record(pose)
            s.leave(pose)
        result = s.solve(identify="offsets")
        s.measure_result()
        s.measure("socket_height", float(result.points()["A"][2]), "length")  # informational: no limit
        verdict = s.judge()
    # no limits section for this script: informational measurements only, and that is never a PASS
    assert verdict["passed"] is None and verdict["status"] == "NO LIMITS"
    assert s.outcome.status == "completed" and s.outcome.stored and s.outcome.report.exists()
    assert s.outcome.verdict == "NO LIMITS" and s.outcome.passed is None and s.outcome.exit_code == 2
    from station.records import open_records, overall_status

    records = open_records(db)
    try:
        stored = records.session(s.outcome.session)
        assert overall_status(stored["verdict"]) == "NO LIMITS"
        assert [r["passed"] for r in records.sessions(serial)] == [None]
    finally:
        records.close()
    listed = station_proc("records", "list", "--serial", serial, "--db", db, module=True, env={"COLUMNS": "80"})
    assert listed.code == 0 and "NO LIMITS" in listed.out and "PASS" not in listed.out, listed.out
    html = s.outcome.report.read_text()
    assert 'id="overall">NO LIMITS<' in html and 'id="overall">PASS' not in html
    hidden = emu.world.hidden()
    for name, p in result.parameters.items():
        if name.startswith("offset.") and p.identifiable:
            assert abs(p.value - hidden[name]) <= 4 * p.std
    header, events = read_journal(s.folder / "journal.jsonl")
    assert header["procedure"] == "test_e2e_scripting" and len(header["procedure_sha256"]) == 64
    assert sum(e["type"] == "sample" for e in events) == 14


def test_manual_touch_by_a_technician(cell):
    emu, cell_path, serial, db = cell
    robot = station.connect(emu.url)
    prompts = []
    target = emu.world.points["A"].position  # the technician sees the socket

    def technician(text):
        prompts.append(text)
        if "onto point" in text:  # jog down towards the socket, then push it in by hand (freedrive)
            q = robot.joint_positions().q
            r = robot.model.ik(target, q, position_only=True)
            robot.move_joints(r.q[0])
            robot.set_compliant(True)

    with station.session(robot, serial, cell=cell_path, options={"n_fit": 9, "n_holdout": 0}, db=db,
                         touch=ManualTouch(prompt=technician, timeout=2.0)) as s:
        plan = s.plan(s.points("socket"), identify="offsets")
        for pose in s.todo(plan):
            s.seat(pose)
            s.record(pose)
            s.leave(pose)
    # 9 poses: the plan needs at least one per unknown (6 offsets + the point's 3 coordinates)
    assert len(s.samples()) == 9 and all(x["status"]["touch"] for x in s.samples())
    assert sum("onto point A" in p for p in prompts) == 9 and sum("clear of point" in p for p in prompts) == 9
    tips = emu.world.truth.position(np.array([x["q"] for x in s.samples()]))
    assert np.abs(tips - target).max() < 1e-4  # every recorded touch is in the socket


def test_script_error_stops_robot_and_keeps_the_journal(cell):
    emu, cell_path, serial, db = cell
    with pytest.raises(RuntimeError, match="operator aborted"), \
            station.session(emu.url, serial, cell=cell_path, db=db) as s:
        plan = s.plan(s.points("socket"), identify="offsets")
        pose = next(s.todo(plan))
        s.approach(pose)
        s.seat(pose)
        s.record(pose)
        raise RuntimeError("operator aborted")
    assert not emu.world.is_moving() and not emu.world.compliant
    _, events = read_journal(s.folder / "journal.jsonl")
    assert [e["type"] for e in events][-2:] == ["fault", "end"] and events[-1]["status"] == "error"
    assert s.outcome.stored and len(s.outcome.record["samples"]) == 1
