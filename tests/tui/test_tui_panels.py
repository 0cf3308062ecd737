"""``station.tui.panels`` and ``station.tui.dialogs``: what the jog UI shows of the arm it drives (joint readings in
degrees against the emulated world's encoders, the tool point in mm against forward kinematics) and what its
questions say."""

from __future__ import annotations

import re

import numpy as np
import pytest
from station.mocks.world import World

from station.tui.approach import NearPlan
from station.tui.controller import JogController
from station.tui.dialogs import near_question, quit_question
from station.tui.panels import joints_text, tcp_text
from station.tui.session import session_header, technician_session

START = [0.1, -0.5, 0.5, 0.2, 0.6, -0.3]


@pytest.fixture
def ctl(tmp_path, robot_rig):
    world = World.default(model="arm6", seed=5, start=START, time_mode="instant")
    _, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
    header = session_header(identity=robot.identity(), model_name="arm6", serial="SN-P", identify="offsets",
                            reference="unknown", url="x")
    c = JogController(robot, technician_session(robot, header, folder=tmp_path / "s"), identify="offsets")
    c.poll(block=True)
    yield world, c
    c.close()


def test_joints_and_tool_as_the_world_has_them(ctl):
    world, c = ctl
    shown = [float(v) for v in re.findall(r"^J\d \S+\s+([+-][\d.]+) deg", joints_text(c, False).plain, re.M)]
    assert shown == pytest.approx(np.degrees(world.encoder_q()), abs=6e-4)  # 3 decimals in deg
    compact = dict(re.findall(r"J(\d)\s+([+-][\d.]+) °", joints_text(c, True).plain))
    assert [float(compact[str(k)]) for k in range(1, 7)] == pytest.approx(shown, abs=1e-9)
    xyz = [float(v) for v in re.findall(r"^[XYZ]\s+([+-][\d.]+) mm", tcp_text(c, False).plain, re.M)]
    assert xyz == pytest.approx(c.model.fk(world.encoder_q())[:3, 3] * 1e3, abs=6e-4)


def test_questions():
    plan = NearPlan("A", [], [], np.eye(4), standoff=0.02, cap=0.25, seconds=30.0, travel=0.4123, reoriented=True,
                    notes=["passes 12 mm from the keep-out 'fixture'"])
    q = near_question(plan, "socket")
    assert q.startswith("Go near A (socket)?") and "20 mm out from A" in q and "412 mm of travel" in q
    assert "raise the speed with + first" in q and "The path passes 12 mm from the keep-out 'fixture'." in q
    assert quit_question(["2 samples not solved"]) == ("Quit station jog?\n\n• 2 samples not solved\n\n"
                                                        "y or ctrl+q quits, n stays.")
