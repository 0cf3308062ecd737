"""``station mock world example --model FILE`` for an arm the station has never seen: the cell it writes is
reachable, checked by an independent computation (the engine's pose planner, which the example code does not
use: a 35 deg cone of tool directions inside the joint limits, every link clear of the floor on touch, approach
and the path between); ``station mock world cell`` warns on a cell with no points and on a point the arm cannot
reach; two different worlds get two serials."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from clirunner import station_proc
from station.mocks.world import World
from station.mocks.world.example import example_text
from station.mocks.world.identity import default_serial

from station.engine.cell import RefPoint
from station.engine.plan import generate_plan
from station.kinematics.collision import KeepOut
from tests.urdf_robots import arm7_urdf, ur5e_urdf


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    d = tmp_path_factory.mktemp("own")
    (d / "myarm.urdf").write_text(ur5e_urdf().replace('name="ur5e_urdf"', 'name="myarm"'))
    r = station_proc("mock", "world", "example", "--model", "myarm.urdf", cwd=d)
    assert r.code == 0, r.err
    (d / "world.yaml").write_text(r.out)
    return d, World.from_file(d / "world.yaml")


@pytest.mark.slow
def test_example_cell_of_an_own_arm_is_reachable(own):
    d, world = own
    sockets = [p for p in world.points.values() if p.kind == "socket"]
    assert len(sockets) >= 3 and any(p.kind == "needle" for p in world.points.values())  # enough for dh_full
    pos = np.array([p.position for p in world.points.values()])
    assert np.min(pos[:, 2]) > 0.02  # above the floor
    assert min(np.linalg.norm(a - b) for i, a in enumerate(pos) for b in pos[i + 1:]) > 0.15  # spread apart
    m = world.nominal
    # the engine's planner, from the world's start pose: every socket from a 35 deg cone, clear of the floor
    for p in sockets:
        ref = RefPoint(p.label, p.kind, p.position, p.approach, p.radius)
        plan = generate_plan(m, [ref], world.encoder_q(), identify="offsets", n_fit=12, n_holdout=2, cone_deg=35.0,
                             keep_out=KeepOut.default(), seed=1)
        assert len(plan.poses) == 14
    # the start pose: inside the limits, every link clear of the floor
    from station.kinematics.collision import Checker

    q0 = world.encoder_q()
    assert np.all((q0 > m.lower) & (q0 < m.upper)) and Checker(m, KeepOut.default()).clear(q0[None])[0]


@pytest.mark.slow
def test_cell_warns_on_no_points_and_unreachable_points(own, tmp_path):
    d, _ = own
    doc = yaml.safe_load((d / "world.yaml").read_text())
    doc["robot"]["model"] = str(d / "myarm.urdf")
    doc["cell"]["points"] = []
    (tmp_path / "empty.yaml").write_text(yaml.safe_dump(doc))
    r = station_proc("mock", "world", "cell", tmp_path / "empty.yaml", "--out", tmp_path / "cell.yaml")
    assert r.code == 0 and "(0 points)" in r.err
    assert "warning" in r.err and "cell.points is empty" in r.err and "mock world example --model" in r.err
    doc["cell"]["points"] = [{"label": "F", "kind": "socket", "position": [3000, 0, 50], "approach": [0, 0, 1]}]
    (tmp_path / "far.yaml").write_text(yaml.safe_dump(doc))
    r = station_proc("mock", "world", "cell", tmp_path / "far.yaml", "--out", tmp_path / "cell.yaml")
    assert r.code == 0 and "cell.points F" in r.err and "0% of a 35 deg cone" in r.err, r.err


def test_two_worlds_two_serials_and_the_same_world_keeps_its_own(own, tmp_path):
    d, world = own
    again = World.from_file(d / "world.yaml")
    assert default_serial(again) == default_serial(world)
    other = World.from_dict(yaml.safe_load(example_text("ur5e")))
    seed1 = World.from_dict(yaml.safe_load(example_text("ur5e", seed=1)))
    serials = {default_serial(world), default_serial(other), default_serial(seed1)}
    assert len(serials) == 3 and all(len(s) == 11 and s.startswith("2023") for s in serials)


def test_example_of_a_seven_axis_arm_has_points(tmp_path):
    f = tmp_path / "arm7.urdf"
    f.write_text(arm7_urdf(masses=False))
    with pytest.raises(Exception, match="--tip-link"):
        example_text(str(f))  # two fingers end the chain: the error names the option that works ...
    (tmp_path / "w.yaml").write_text(example_text(str(f), tip_link="ball"))  # ... which example takes
    w = World.from_file(tmp_path / "w.yaml")
    assert sum(p.kind == "socket" for p in w.points.values()) >= 1


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ur3e", "ur5e", "ur10e", "arm6"])
def test_example_of_a_builtin_six_axis_arm_has_three_reachable_sockets(name):
    """The example world of a built-in 6-axis arm carries three sockets (its default cell plus the example's), each
    reachable from the plan's cone by the engine's planner from the world's start pose: dh_full runs on it."""
    world = World.from_dict(yaml.safe_load(example_text(name)))
    sockets = [p for p in world.points.values() if p.kind == "socket"]
    assert len(sockets) >= 3
    for p in sockets:
        plan = generate_plan(world.nominal, [RefPoint(p.label, p.kind, p.position, p.approach, p.radius)],
                             world.encoder_q(), identify="offsets", n_fit=10, n_holdout=2, cone_deg=35.0,
                             keep_out=KeepOut.default(), seed=1)
        assert len(plan.poses) == 12, (name, p.label)
