"""The simulated world knows the table and the fixtures as truth: a link of the TRUE robot touching them is a
recorded collision, with ``cell.collision: stop`` also a protective stop (a colliding synchronised move is
refused before it starts, a velocity jog stops at contact); world files carry the keep-outs in their units
and the station-side cell file exports them with the station's clearance."""

import numpy as np
import pytest
import yaml
from station.mocks.world import World, WorldFileError

from station.engine.cell import cell_from_dict
from station.kinematics.chain import forward
from station.kinematics.collision import Box

START = [0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]
ELBOW_DOWN = [0.0, 0.6, 0.0, 0.0, 0.0, 0.0]  # upper arm 34 deg below horizontal: the elbow 80 mm under the table


def _elbow_z(world):
    m = world.truth
    _, prefix = forward(m.chain, world.encoder_q()[None], m.params, keep_prefix=True)
    return prefix[0, int(np.flatnonzero(m.chain.joint == 2)[0]), 2, 3]


def test_a_synchronised_move_into_the_table_is_refused_with_a_protective_stop():
    w = World.default("ur5e", seed=1, cell={"collision": "stop"})
    q0 = w.encoder_q()
    w.command_q(ELBOW_DOWN)
    w.run_until_idle()
    np.testing.assert_allclose(w.encoder_q(), q0)  # nothing moved
    assert w.protective_stopped
    assert len(w.collisions) == 1 and w.collisions[0].startswith("command_q refused: link ")
    assert "'mounting plane' (clearance 0 mm)" in w.collisions[0]
    w.command_q(START)  # refused while stopped
    assert w.protective_stopped and np.allclose(w.encoder_q(), q0)


def test_by_default_the_world_records_the_contact_and_lets_the_arm_through():
    w = World.default("ur5e", seed=1)  # cell.collision: record
    w.command_q(ELBOW_DOWN)
    w.run_until_idle()
    assert _elbow_z(w) < -0.05 and not w.protective_stopped
    assert w.collisions and w.collisions[0].startswith("collision: link ")
    w.command_q(START)  # leaving the table is not another collision
    w.run_until_idle()
    assert len(w.collisions) == 1


def test_a_velocity_jog_down_stops_at_contact():
    w = World.default("ur5e", seed=1, cell={"collision": "stop"}, time_mode="sim")
    w.command_q([0.0, -0.2, 0.0, -1.5708, 0.0, 0.0])  # arm forward, a little up
    w.run_until_idle()
    assert not w.collisions
    qd = np.zeros(6)
    qd[1] = 0.2  # shoulder down at 0.2 rad/s: the arm sweeps towards the table
    w.command_qd(qd)
    for _ in range(400):  # 2 s in 5 ms observations (an emulator polls at least this often)
        w.advance(0.005)
        w.encoder_q()
        if w.protective_stopped:
            break
    assert w.protective_stopped and w.collisions[0].startswith("collision: link ")
    assert not w.is_moving()
    # stopped at the contact: at most one watch period (10 ms) of motion past it
    from station.kinematics.collision import Checker

    margin = Checker(w.truth, w.spec.keep_out).margins(w.encoder_q()[None]).min()
    assert -0.2 * 0.01 * 1.4 - 1e-4 <= margin < 0


def test_world_file_keep_out_in_mm_round_trips_and_reaches_the_station_cell(tmp_path):
    doc = {"format": "station-world/1", "units": {"length": "mm", "angle": "deg"}, "robot": {"model": "ur5e"},
           "cell": {"collision": "stop", "mounting": {"offset": -5},
                    "keep_out": [{"name": "camera", "box": {"center": [-700, 0, 200], "size": [200, 300, 400],
                                                            "rotation": {"rz": 20}}}]}}
    p = tmp_path / "w.yaml"
    p.write_text(yaml.safe_dump(doc))
    w = World.from_file(p)
    box = w.spec.keep_out.obstacles[0]
    assert isinstance(box, Box) and box.clearance == 0.0 and w.spec.keep_out.mounting.offset == pytest.approx(-0.005)
    again = World.from_dict(w.to_dict("mm", "deg"))
    b2 = again.spec.keep_out.obstacles[0]
    np.testing.assert_allclose([b2.center, b2.half], [box.center, box.half], atol=1e-12)
    np.testing.assert_allclose(b2.rotation, box.rotation, atol=1e-9)
    assert again.spec.collision == "stop"
    cell = cell_from_dict(yaml.safe_load(yaml.safe_dump(w.station_cell())), "exported")
    sb = cell.keep_out.obstacles[0]
    np.testing.assert_allclose([sb.center, sb.half], [box.center, box.half], atol=1e-9)
    assert sb.clearance == pytest.approx(0.01) and cell.keep_out.mounting.offset == pytest.approx(-0.005)
    w.command_q([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # the stretched arm lies across the camera
    assert w.protective_stopped and "obstacle 'camera'" in w.collisions[0]


@pytest.mark.parametrize("cell, field", [
    ({"collision": "crash"}, "cell.collision"),
    ({"keep_out": [{"name": "b", "box": {"min": [0, 0, 0], "max": [0, 1, 1]}}]}, r"keep_out\[0\] \(b\)\.box: max"),
])
def test_malformed_world_keep_out_is_one_line(cell, field):
    with pytest.raises(WorldFileError, match=field):
        World.default("ur5e", cell=cell)
