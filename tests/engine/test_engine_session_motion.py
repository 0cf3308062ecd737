"""What the session offers a procedure that plans and moves on its own (``correction_map``, ``iso9283``):
``s.journaled_plan()`` (a resume reuses the journaled poses), ``s.keep_out``/``s.checker()`` (the cell's keep-outs),
``s.move_along(targets, what)`` (a collision-checked path, each move checked for disk space) and
``s.instrument_sigma(distance)`` (the noise the instrument states for itself). arm6 on the CANopen emulator (real
canopen and python-can libraries on a virtual channel); the truth is the world's joint state."""

from __future__ import annotations

import numpy as np
import pytest
from station.mocks.launch import launch
from station.mocks.tracker.config import tracker_config
from station.mocks.tracker.server import TrackerServer
from station.mocks.world import World

import station
from station.engine import events as ev
from station.engine.plan import PlanError, PlannedPose, PosePlan
from station.robot.errors import ConfigError

SERIAL = "A6-0077"
SLACK = "&sdo_timeout_ms=2000&heartbeat_ms=1000"  # the emulator shares this process (and a busy CI host)


@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world = World.default("arm6", seed=2)
    with launch("canopen", world, serial=SERIAL) as emu:
        yield world, emu.url + SLACK, f"sqlite:///{tmp_path / 'r.db'}"


def test_plan_path_and_keep_outs(rig):
    world, url, db = rig
    q0 = world.encoder_q().copy()
    q1 = q0 + np.array([0.1, -0.05, 0.05, 0.1, 0.1, 0.1])
    with station.session(url, SERIAL, db=db, report=False) as s:
        assert s.journaled_plan() is None  # nothing journaled yet: the procedure plans
        assert s.keep_out is None and s.checker().keep_out.mounting is not None  # no cell: the default floor
        s.event(ev.Plan(plan=PosePlan([PlannedPose(0, "T", q1.tolist(), q1.tolist())], {"mine": 1}).to_dict()))
        plan = s.journaled_plan()
        assert s.current_plan is plan and plan.settings == {"mine": 1} and np.allclose(plan.poses[0].q, q1)
        s.move_along([q0 + (q1 - q0) / 2, q1], "the test path")
        assert np.allclose(world.encoder_q(), q1, atol=1e-6)  # the world's joints: where it was sent
        assert s.checker().hits(q1[None])[0] is None
        down = q1.copy()
        down[1] += 2.0  # shoulder far down: the arm through its own mounting plane
        with pytest.raises(PlanError, match="the dive: .* inside obstacle .mounting plane."):
            s.move_along([down], "the dive")
        assert np.allclose(world.encoder_q(), q1, atol=1e-6)  # refused before anything moved


def test_a_journaled_plan_for_another_robot_is_one_line(rig):
    world, url, db = rig
    with pytest.raises(ConfigError, match=r"pose 0 has 4 joint values, the robot's model arm6 has 6"), \
            station.session(url, SERIAL, db=db, report=False) as s:
        s.event(ev.Plan(plan=PosePlan([PlannedPose(0, "T", [0.0] * 4, [0.0] * 4)]).to_dict()))
        s.journaled_plan()


def test_the_instrument_states_its_noise(rig):
    world, url, db = rig
    cfg = tracker_config({"noise": False})
    with TrackerServer(world, cfg) as trk, \
            station.session(url, SERIAL, options={"tracker": trk.url}, db=db, report=False) as s:
        assert s.instrument_sigma(2.0) is None  # no instrument yet: nothing stated
        s.instrument("tracker")
        # the tracker's specification (docs/hardware.md): 15 um + 6 um/m per axis, 1 sigma
        assert s.instrument_sigma(2.0) == pytest.approx(27e-6)
        assert np.allclose(s.instrument_sigma(np.array([0.0, 1.0])), [15e-6, 21e-6])
