"""``station.engine.writeback``: the write-back transaction on the real CANopen driver and emulated drives: the
pre-image journaled and backed up before anything is written, the read-back within one encoder count, a new arm
that then reads the world's joints shifted by the written offsets, the restore, and where an interrupted
write-back stands."""

from __future__ import annotations

import json
from functools import partial

import numpy as np
import pytest
from station.mocks.world import World

from station.engine.events import Writeback
from station.engine.writeback import (
    BACKUP,
    apply,
    count_tolerance,
    load_backup,
    plan_write,
    read_device,
    restore,
    resume_point,
)
from station.kinematics import load_model
from station.robot.errors import StationError

START = [0.1, -0.5, 0.5, 0.2, 0.6, -0.3]


def test_write_read_back_and_restore(tmp_path, robot_rig):
    world = World.default(model="arm6", seed=5, start=START, time_mode="instant")
    _, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
    model = load_model("arm6")
    tol = partial(count_tolerance, model)
    before = read_device(robot)
    q_before = robot.joint_positions().q.copy()
    plan = plan_write(before, {"offset.j2": 0.002, "offset.j3": -0.001})
    events: list = []
    back = apply(robot, plan, event=events.append, folder=tmp_path, session="S-1", tolerance=tol)
    assert [e.phase for e in events] == ["pre-image", "written"]
    assert abs(back["offset.j2"] - before["offset.j2"] - 0.002) <= tol("offset.j2")
    doc = json.loads((tmp_path / BACKUP).read_text())
    assert doc["before"] == before and load_backup(tmp_path)["session"] == "S-1"
    # the arm did not move: its joints now read the world's positions through the new offsets
    dq = robot.joint_positions().q - q_before
    assert np.abs(dq - np.array([0, 0.002, -0.001, 0, 0, 0])).max() <= 2 * tol("offset.j2")
    assert resume_point(events, read_device(robot), tol)[1] == "written"
    restore(robot, tmp_path, "S-1", event=events.append, tolerance=tol)
    assert all(abs(read_device(robot)[k] - before[k]) <= tol(k) for k in before)
    assert events[-1].kind == "restore" and events[-1].phase == "written"
    assert resume_point(events, read_device(robot), tol)[1] == "pre-image"


def test_resume_points_and_a_missing_backup(tmp_path):
    tol = partial(count_tolerance, load_model("arm6"))
    pre = Writeback(phase="pre-image", kind="write", before={"offset.j1": 0.0, "offset.j2": 0.0},
                    after={"offset.j1": 0.001, "offset.j2": 0.002})
    assert resume_point([], {}, tol) == (None, None)
    assert resume_point([pre], {"offset.j1": 0.001, "offset.j2": 0.0}, tol)[1] == "partial"
    assert resume_point([pre], {"offset.j1": 0.5, "offset.j2": 0.0}, tol)[1] == "unknown"
    with pytest.raises(StationError, match="no backup"):
        load_backup(tmp_path)
