"""``station.drivers.ur.identity``: the arm a model is for against what the dashboard server reports (``get
robot model`` and ``PolyscopeVersion``, UR Dashboard Server manual: CB3 3.x, e-Series 5.x, PolyScope X 10.x)."""

from __future__ import annotations

import pytest
from station.drivers.ur.identity import check_arm, expected_arm, series_of

from station.robot.errors import IdentityMismatch


def test_the_arm_a_model_names():
    assert expected_arm("ur5e", None) == ("UR5", "e-Series")
    assert expected_arm("ur10", None) == ("UR10", "CB3")
    assert expected_arm("ur20", None) == ("UR20", "e-Series")  # no "e" in its name, e-Series generation
    assert expected_arm("myarm", "UR3e") == ("UR3", "e-Series") and expected_arm("myarm", None) is None


@pytest.mark.parametrize("reply, series", [("URSoftware 3.15.7.106331 (Jan 2022)", "CB3"),
                                           ("URSoftware 5.15.0.1234", "e-Series"), ("PolyScope X 10.7.0", "e-Series"),
                                           ("no version", None)])
def test_series_from_the_polyscope_version(reply, series):
    assert series_of(reply) == series


def test_matching_arms_pass_and_read_as_users_write_them():
    assert check_arm("h", "ur5e", None, "UR5", "URSoftware 5.15.0") == "UR5e"
    assert check_arm("h", "ur10", None, "UR10\n", "URSoftware 3.15.7") == "UR10 (CB3)"
    assert check_arm("h", "ur20", None, "UR20", "URSoftware 5.16") == "UR20"
    assert check_arm("h", "cell7", "UR5e", "UR5", "URSoftware 5.12") == "UR5e"


@pytest.mark.parametrize("model, robot_type, reported, polyscope, needle", [
    ("ur3e", None, "UR5", "URSoftware 5.15", "model ur3e is a UR3 e-Series but the controller reports UR5 "
                                             "e-Series ('URSoftware 5.15'); nothing was moved: use model=ur5e"),
    ("ur5e", None, "UR5", "URSoftware 3.15", "reports UR5 CB3"),  # a CB3 table on... the other generation
    ("cell7", None, "UR5", "URSoftware 5.15", "add robot_type=UR5e to the robot URL"),
    ("cell7", "ABB", "UR5", "URSoftware 5.15", "robot_type=ABB names no UR arm"),
    ("ur5e", None, "KUKA", "URSoftware 5.15", "reports robot model 'KUKA', not a UR arm"),
])
def test_a_wrong_arm_is_refused_in_one_line(model, robot_type, reported, polyscope, needle):
    with pytest.raises(IdentityMismatch) as e:
        check_arm("10.0.0.5", model, robot_type, reported, polyscope)
    assert str(e.value).startswith("ur://10.0.0.5: ") and needle in str(e.value) and "\n" not in str(e.value)
