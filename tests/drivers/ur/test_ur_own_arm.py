"""An integrator's own 6-axis arm (a URDF) on the emulated UR controller: ``station mock ur --world`` prints a robot
URL that works as printed, and every identity error on the way names the fix that works."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from clirunner import station_proc
from station.mocks.world import World, default_doc

from station.robot import IdentityMismatch, open_robot
from tests.urdf_robots import arm7_urdf, ur5e_urdf

START = [0.1, -1.45, 1.6, -1.72, -1.5708, 0.2]


def _own_arm_world(tmp_path, urdf_text: str, start=START, **robot) -> tuple:
    (tmp_path / "myarm.urdf").write_text(urdf_text.replace('name="ur5e_urdf"', 'name="myarm"'))
    doc = default_doc("ur5e", seed=12)
    doc["robot"] = {"model": "myarm.urdf", **robot}  # relative to the world file, as an integrator writes it
    doc["errors"] = {"random": {"dh": {"length": 2e-4, "angle": 3e-4}}}
    doc["motion"].update(time_mode="sim")
    if start is not None:
        doc["motion"]["start"] = list(start)
    doc["buses"] = {"ur": {"serial": "20235500990"}}
    doc.pop("cell", None)
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path, World.from_file(path)


@pytest.mark.slow
def test_own_urdf_arm_runs_with_the_url_the_emulator_prints(tmp_path, emulators):
    path, world = _own_arm_world(tmp_path, ur5e_urdf())
    emu = emulators("ur", path)
    url = emu.url
    assert "robot_type=UR5e" in url and "power_on=yes" in url and str(tmp_path / "myarm.urdf") in url
    with open_robot(url) as robot:  # as printed
        assert robot.model.name == "myarm" and robot.arm == "UR5e"
        # the controller's calibration, fitted into the URDF's chain: the world's true arm up to a constant
        # transform at the base (plain DH starts at joint 1's axis: where that axis sits on the mounting is no
        # part of a controller's table, the cell calibration finds it as a base error)
        keep = {n: world.nominal.param(n) for n in world.truth.param_names if n.startswith(("offset.", "base.",
                                                                                             "tcp."))}
        truth = world.truth.with_params(keep)
        q = np.random.default_rng(1).uniform(-3, 3, size=(20, 6))
        C = truth.fk(q[0]) @ np.linalg.inv(robot.model.fk(q[0]))
        np.testing.assert_allclose(C @ robot.model.fk(q), truth.fk(q), atol=1e-9)
        assert np.max(np.abs(robot.model.fk(q) - world.nominal.fk(q))) > 1e-5  # not the nominal
        robot.enable()
        q0 = robot.joint_positions().q
        robot.move_joints(q0 + 0.05, speed=1.0)
        np.testing.assert_allclose(robot.joint_positions().q, q0 + 0.05, atol=1e-9)


def test_identity_errors_for_an_own_arm_name_the_fix_that_works(tmp_path, emulators):
    path, _ = _own_arm_world(tmp_path, ur5e_urdf())
    emu = emulators("ur", path)
    model = tmp_path / "myarm.urdf"
    with pytest.raises(IdentityMismatch) as e:
        open_robot(f"ur://{emu.host}?model={model}")
    msg = str(e.value)
    assert "add robot_type=UR5e" in msg and "\n" not in msg
    with pytest.raises(IdentityMismatch, match="use robot_type=UR5e only if"):
        open_robot(f"ur://{emu.host}?model={model}&robot_type=UR10e")
    with open_robot(f"ur://{emu.host}?model={model}&robot_type=UR5e") as robot:  # the fix, as named
        assert robot.arm == "UR5e"


def test_mock_ur_refuses_an_arm_a_ur_controller_cannot_drive(tmp_path):
    path, _ = _own_arm_world(tmp_path, arm7_urdf(), start=None, tip_link="ball")
    out = station_proc("mock", "ur", "--host", "127.0.0.1", "--world", path, timeout=60)
    assert out.code == 2 and out.err.count("\n") == 1
    assert "station: error:" in out.err and "7 joints" in out.err and "6 revolute joints" in out.err


def test_mock_ur_refuses_bad_bus_settings_in_one_line(tmp_path):
    """buses.ur as a controller could be: an unknown key, a robot model no controller reports, an unknown
    calibration choice or a negative time are one line naming the field (``station mock ur`` prints it)."""
    from station.mocks.ur.cli import controller_for

    path, _ = _own_arm_world(tmp_path, ur5e_urdf())
    doc = yaml.safe_load(path.read_text())
    for bad, needle in (({"robot_model": "MYARM"}, "buses.ur.robot_model"), ({"calibration": "some"},
                                                                             "buses.ur.calibration"),
                        ({"power_on_s": -1}, "buses.ur.power_on_s"), ({"bogus": 1}, "unknown key")):
        doc["buses"]["ur"] = {"serial": "20235500990", **bad}
        path.write_text(yaml.safe_dump(doc))
        with pytest.raises(ValueError, match=needle) as e:
            controller_for(World.from_file(path))
        assert "\n" not in str(e.value)
