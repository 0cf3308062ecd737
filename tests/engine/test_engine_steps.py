"""One step mechanism (``station.engine.steps``), traced as labgrid traces its ``@step``: every step of a session
journals its start with its arguments and its end (done/failed with the duration, or skipped with the reason);
steps nest; a fault, an abort and the record name the innermost step and its pose."""

from __future__ import annotations

import time

import pytest
from clirunner import station_main
from faultrig import demo_cell

from station.api import run as start
from station.cli.run_cmd import BUS_OPTIONS
from station.engine import events as ev
from station.engine.journal import Journal, JournalWriteError, read_journal
from station.engine.session import Session
from station.engine.session_record import session_from_journal
from station.engine.steps import Steps, step, summarize
from station.engine.touch import SocketSeating
from station.report import write_report
from station.report.content import steps_rows
from station.robot.errors import DeviceFault


# ---- the mechanism alone ---------------------------------------------------------------------------------------
def test_nested_steps_journal_start_and_end_and_the_innermost_claims_the_failure():
    journal: list[ev.Step] = []
    steps = Steps(journal.append)
    with pytest.raises(DeviceFault), steps.run("outer", {"identify": "offsets"}):
        assert steps.current.name == "outer"
        with steps.run("inner", {"pose": 3}):
            assert steps.current.describe() == "inner of pose 3" and steps.current.parent.name == "outer"
            time.sleep(0.02)
            raise DeviceFault("lost the seat")
    assert steps.current is None
    assert [(e.name, e.status) for e in journal] == [("outer", "start"), ("inner", "start"), ("inner", "failed"),
                                                     ("outer", "failed")]
    assert journal[0].info == {"identify": "offsets"} and journal[1].info == {"pose": 3}
    assert journal[2].error == "DeviceFault" and journal[2].message == "lost the seat"
    assert 0.02 <= journal[2].duration <= journal[3].duration
    try:
        raise DeviceFault("another")
    except DeviceFault as other:
        assert steps.failed_for(other) is None  # raised outside every step
    failed = steps.failed
    assert failed.name == "inner" and failed.pose == 3


def test_a_failed_event_that_cannot_be_written_leaves_the_fault_as_it_was():
    def journal(event):
        if event.status == "failed":
            raise JournalWriteError("disk full")

    with pytest.raises(DeviceFault, match="the fault"), Steps(journal).run("seat", {"pose": 1}):
        raise DeviceFault("the fault")


def test_a_technician_action_goes_on_when_its_trace_cannot_be_written():
    lost, done = [], []

    def journal(event):
        raise JournalWriteError("disk full")

    with Steps(journal, on_lost=lambda name, err: lost.append((name, str(err)))).run("compliant off", {}):
        done.append(True)
    assert done == [True] and lost == [("compliant off", "disk full")] * 2


def test_the_decorator_binds_the_named_arguments_of_a_procedure_helper(tmp_path):
    class Pose:  # what a PlannedPose offers the trace: its index
        index, approach_q = 7, [0.0]

    journal = Journal.create(tmp_path / "journal.jsonl", {"session": "S", "serial": "SN", "procedure": "p"})
    s = Session(journal, None, model=_model())

    @step(args=("pose", "speed", "label"))
    def move(s, pose, speed=0.25, label=None):
        return s.steps.current.info

    assert move(s, Pose()) == {"pose": 7, "speed": 0.25}  # defaults applied, None left out
    journal.close()
    events = [e for e in read_journal(journal.path)[1] if e.type == "step"]
    assert [(e.name, e.status, e.info) for e in events] == [("move", "start", {"pose": 7, "speed": 0.25}),
                                                          ("move", "done", {})]
    assert events[1].duration >= 0


def test_summary_counts_runs_and_ends_steps_left_open_by_a_crash():
    def st(name, status, **kw):
        return ev.Step(name=name, status=status, t=100.0, **kw)

    events = [st("connect", "start"), st("connect", "done", duration=0.1),
              st("approach", "start", info={"pose": 0}), st("approach", "done", duration=1.0),
              st("approach", "start", info={"pose": 1}),  # the process died here
              ev.Resume(samples_kept=0, events_before=5),
              st("approach", "start", info={"pose": 1}), st("approach", "failed", duration=0.5, error="E", message="m"),
              st("write_back", "skipped", reason="not requested (--apply)")]
    out = {e["name"]: e for e in summarize(events)}
    a = out["approach"]
    assert (a["runs"], a["done"], a["failed"], a["unfinished"], a["duration_s"]) == (3, 1, 1, 1, 1.5)
    assert [n["status"] for n in a["not_done"]] == ["unfinished", "failed"]
    assert a["not_done"][1]["info"] == {"pose": 1} and a["not_done"][1]["message"] == "m" and a["info"] == {}
    assert out["connect"]["info"] == {} and out["connect"]["done"] == 1
    assert out["write_back"]["not_done"][0]["reason"] == "not requested (--apply)"


def _model():
    from station.kinematics import load_model

    return load_model("omx")


# ---- a real session -----------------------------------------------------------------------------------------------
@pytest.fixture
def cell(tmp_path, monkeypatch):
    with demo_cell("canopen", tmp_path, seed=21) as c:
        monkeypatch.setenv("STATION_HOME", str(c.home))
        yield c


def _pairs(events) -> list[tuple]:
    """(name, info of the start, outcome, duration) of every step, and the nesting depth, from journal order."""
    out, stack = [], []
    for e in events:
        if e.type != "step":
            continue
        if e.status == "start":
            stack.append((e.name, e.info, len(stack)))
        elif e.status == "skipped":
            out.append((e.name, e.info, "skipped", None, len(stack)))
        else:
            name, info, depth = stack.pop()
            assert name == e.name, (name, e.name)
            out.append((name, info, e.status, e.duration, depth))
    assert not stack
    return out


def test_every_step_of_a_run_is_traced_with_its_arguments_and_duration_and_nests(cell):
    out = start("zero_offsets", cell.url, cell.serial, cell=cell.cell_path, db=cell.db, apply=True, report=False,
                options={**BUS_OPTIONS["canopen"], "n_fit": 12, "n_holdout": 2})
    assert out.status == "completed", out.error
    events = read_journal(out.folder / "journal.jsonl")[1]
    pairs = _pairs(events)
    assert all(d is not None and d >= 0 for _, _, status, d, _ in pairs if status != "skipped")
    top = [(n, i) for n, i, _, _, depth in pairs if depth == 0]
    assert [n for n, _ in top[:3]] == ["connect", "check_state", "plan"]
    n_poses = len([e for e in events if e.type == "sample"])
    for action in ("approach", "seat", "record", "leave"):  # each pose-loop action is a step naming its pose
        poses = [i["pose"] for n, i in top if n == action]
        assert sorted(poses) == list(range(14)), (action, poses)
    assert ("solve", {"identify": "offsets"}) in top and ("judge", {}) in top
    assert out.passed, out.record["verdict"]  # so that it writes back: its check touch nests in write_back
    inner = [(n, depth) for n, _, _, _, depth in pairs if depth == 1]
    assert ("approach", 1) in inner and ("seat", 1) in inner and ("write_back", {}) in top
    # the record lists them, and so do `station records show` and the report
    steps = session_from_journal(out.folder)["steps"]
    rec = {e["name"]: e for e in steps if e["parent"] is None}
    assert rec["approach"]["runs"] == n_poses and rec["approach"]["done"] == n_poses
    check = [(e["name"], e["depth"], e["info"]) for e in steps if e["parent"] == "write_back"]
    assert [c[:2] for c in check] == [("approach", 1), ("seat", 1), ("leave", 1)] and "pose" in check[0][2]
    assert rec["solve"]["info"] == {"identify": "offsets"} and rec["solve"]["duration_s"] > 0
    assert rec["connect"]["started"].endswith("Z")
    code, shown, err = station_main("records", "show", cell.serial, "--db", cell.db)
    assert code == 0, err
    table = [line.replace("│", " ").split() for line in shown[shown.index("Steps"):].splitlines()]
    assert ["approach", str(n_poses), "done"] == table[[r[:1] for r in table].index(["approach"])][:3], table
    solve = next(r for r in table if r[:1] == ["solve"])
    assert solve[1:3] == ["1", "done"] and solve[-1] == "identify=offsets", table
    nested = [r for r in table if r[:1] == ["approach"]][1]  # the write-back's check touch, below write_back
    assert nested[1:3] == ["1", "done"] and nested[-1].startswith("pose="), table
    html = write_report(out.record, out.folder).read_text()
    assert '<table id="steps">' in html and "identify=offsets" in html


def test_a_fault_names_the_innermost_step_and_its_pose(cell):
    class SlipsAtPose2(SocketSeating):
        def bring_to(self, s, pose):
            if pose.index == 2:
                raise DeviceFault("the ball slipped out of the socket")
            super().bring_to(s, pose)

    out = start("zero_offsets", cell.url, cell.serial, cell=cell.cell_path, db=cell.db, touch=SlipsAtPose2(),
                report=False, options={**BUS_OPTIONS["canopen"], "n_fit": 12, "n_holdout": 2})
    assert out.status == "error" and out.exit_code == 2
    events = read_journal(out.folder / "journal.jsonl")[1]
    fault = next(e for e in events if e.type == "fault")
    assert (fault.step, fault.pose, fault.error) == ("seat", 2, "DeviceFault")
    failed = [e for e in events if e.type == "step" and e.status == "failed"]
    assert [(e.name, e.error) for e in failed] == [("seat", "DeviceFault")] and failed[0].duration >= 0
    rec = {e["name"]: e for e in session_from_journal(out.folder)["steps"]}
    assert rec["seat"]["not_done"] == [{"status": "failed", "info": {"pose": 2}, "started": rec["seat"]["not_done"][0][
        "started"], "error": "DeviceFault", "message": "the ball slipped out of the socket"}]
    assert [r for r in steps_rows({"steps": list(rec.values())}) if r["name"] == "seat"][0]["notes"] == [
        "pose 2: DeviceFault: the ball slipped out of the socket"]
