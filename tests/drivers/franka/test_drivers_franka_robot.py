"""``station.drivers.franka.robot`` without a robot (``connect=False``): the URL options as declared (the seating
press among them), what is refused before anything is sent, the calibration export. Against franka-sim:
tests/drivers/franka/test_franka_driver.py."""

from __future__ import annotations

import json

import numpy as np
import pytest
from station.drivers.franka.robot import FrankaRobot

from station.kinematics import load_model
from station.robot.errors import ConfigError, LimitError
from station.robot.url import parse_url

URL = "franka://127.0.0.2?model=fr3"


def _robot(query: str = "") -> FrankaRobot:
    return FrankaRobot.from_url(parse_url(URL + query), connect=False)


def test_options_and_their_defaults():
    r = _robot()
    assert (r.press_force, r.stiffness, r.contact_force, r.motion, r.speed) == (5.0, 600.0, 2.0, "async", 0.5)
    r = _robot("&press_force=0&stiffness=1000&contact_force=1.5&motion=stream&speed=1.5&serial=FR3-1")
    assert (r.press_force, r.stiffness, r.contact_force, r.motion, r.speed, r.serial) == (
        0.0, 1000.0, 1.5, "stream", 1.5, "FR3-1")


@pytest.mark.parametrize("query, word", [
    ("&press_force=25", "press_force"),  # above the collision thresholds the driver sets (20 N): a reflex
    ("&press_force=-1", "press_force"),
    ("&stiffness=5", "stiffness"),  # Franka's range for setCartesianImpedance: [10, 3000] N/m
    ("&speed=3", "speed"),  # above the slowest joint's 2.62 rad/s
    ("&motion=teleport", "motion"),
])
def test_out_of_range_options_are_one_line_config_errors(query, word):
    with pytest.raises(ConfigError, match=word) as e:
        _robot(query)
    assert "\n" not in str(e.value)


def test_a_port_or_a_missing_host_is_refused():
    with pytest.raises(ConfigError, match="takes no port"):
        FrankaRobot.from_url(parse_url("franka://127.0.0.2:1337?model=fr3"), connect=False)


def test_targets_beyond_the_joint_limits_are_refused_before_anything_is_sent():
    r = _robot()  # not connected: anything sent would fail otherwise than with a LimitError
    q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    q[3] = 0.1  # joint 4 (the elbow) has a negative upper limit on an FR3
    with pytest.raises(LimitError):
        r.move_joints(q)


def test_export_writes_the_calibrated_model_and_leaves_the_robot_alone(tmp_path):
    r = _robot("&serial=FR3-7")
    fr3 = load_model("fr3")
    name = next(n for n in fr3.param_names if n.startswith("offset."))
    paths = r.export_calibration({name: fr3.param(name) + 1e-4}, tmp_path / "out")
    assert [p.name for p in paths] == ["fr3_calibrated.urdf", "fr3_calibrated.yaml", "calibration.json"]
    doc = json.loads(paths[2].read_text())
    assert doc["serial"] == "FR3-7" and doc["values"][name] == pytest.approx(fr3.param(name) + 1e-4)
    assert load_model(str(paths[1])).param(name) == pytest.approx(fr3.param(name) + 1e-4)
    with pytest.raises(ConfigError):
        r.export_calibration(42, tmp_path)
