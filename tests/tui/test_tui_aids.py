"""``station.tui.aids``: the proximity cue to the selected cell point, against forward kinematics of the emulated
arm's readings and the cell's point; what can be seated on a robot with a compliant mode."""

from __future__ import annotations

import numpy as np
import pytest
from station.mocks.world import World

from station.engine.cell import cell_from_dict
from station.tui.aids import ApproachAids
from station.tui.controller import JogController
from station.tui.session import session_header, technician_session

START = [0.0, -0.5, 0.5, 0.0, 0.6, 0.0]


def test_proximity_to_the_selected_point(tmp_path, robot_rig):
    world = World.default(model="arm6", seed=5, start=START, time_mode="instant")
    _, robot = robot_rig("canopen", world, query="&heartbeat_ms=250")
    cell = cell_from_dict(world.station_cell())
    header = session_header(identity=robot.identity(), model_name="arm6", serial="SN-A", identify="offsets",
                            reference="unknown", url="x")
    ctl = JogController(robot, technician_session(robot, header, folder=tmp_path / "s"), identify="offsets",
                        cell=cell)
    try:
        aids = ctl.aids
        assert isinstance(aids, ApproachAids) and set(aids.targets) == set(cell.points)
        assert aids.can_seat and not aids.blocked  # CiA 402 drives have a compliant (torque) mode
        ctl.poll(block=True)
        for _ in range(len(cell.points)):
            p = aids.proximity
            point = cell.points[ctl.point].position
            tool = ctl.model.fk(world.encoder_q())[:3, 3]
            # (the readout is in drive counts: within one count of the world at the tool)
            assert p.label == ctl.point and p.distance == pytest.approx(np.linalg.norm(point - tool), abs=1e-6)
            assert np.linalg.norm(p.delta) == pytest.approx(p.distance, abs=1e-9)
            assert p.above ** 2 + p.lateral ** 2 == pytest.approx(p.distance ** 2, rel=1e-9)
            ctl.next_point()
            ctl.poll(block=True)
    finally:
        ctl.close()
