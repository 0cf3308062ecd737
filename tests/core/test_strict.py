"""``station.strict``: a format's schema as ``Strict`` models; the first problem of a file as one line
``FILE:LINE: FIELD: what is wrong`` (the line read from the YAML text itself)."""

from __future__ import annotations

import pytest

from station.strict import Name, Pos, Strict, Vec3, check, finite
from station.yamlfile import parse_yaml_doc


class Bad(Exception):
    pass


class Joint(Strict):
    name: Name
    mass: Pos
    axis: Vec3


class Robot(Strict):
    model: Name
    joints: list[Joint]


GOOD = """model: arm
joints:
  - name: j1
    mass: 2.5
    axis: [0, 0, 1]
  - name: j2
    mass: 1.0
    axis: [0, 1, 0]
"""


def load(text: str) -> Robot:
    return check(Robot, parse_yaml_doc(text, Bad, "robot.yaml"), Bad)


def test_a_good_file_validates():
    r = load(GOOD)
    assert [j.name for j in r.joints] == ["j1", "j2"] and r.joints[1].axis == [0.0, 1.0, 0.0]


@pytest.mark.parametrize("old, new, expect", [
    ("    mass: 1.0", "    mass: 1.0\n    colour: red",
     "robot.yaml:8: joints[1]: expected a mapping of name, mass, axis; unknown key 'colour' (misspelt?)"),
    ("    mass: 1.0", "    mass: -1.0", "robot.yaml:7: joints[1].mass: must be positive, got -1.0"),
    ("    mass: 1.0", "    mass: true", "robot.yaml:7: joints[1].mass: expected a number, got True"),
    ("    mass: 1.0", '    mass: "1.0"', "robot.yaml:7: joints[1].mass: expected a number, got '1.0'"),
    ("    mass: 1.0", "    mass: .nan", "robot.yaml:7: joints[1].mass: not a finite number"),
    ("    mass: 2.5", "    mass: 1e12", "robot.yaml:4: joints[0].mass: "),
    ("    axis: [0, 1, 0]", "    axis: [0, 1]", "robot.yaml:8: joints[1].axis: expected [x, y, z], got [0, 1]"),
    ("model: arm\n", "", "robot.yaml: expected key 'model' (missing)"),
])
def test_the_first_problem_is_one_line_with_file_line_and_field(old, new, expect):
    assert old in GOOD
    with pytest.raises(Bad) as e:
        load(GOOD.replace(old, new, 1))
    msg = str(e.value)
    assert msg.startswith(expect) and "\n" not in msg, msg


def test_plain_data_is_named_by_the_caller():
    with pytest.raises(Bad, match=r"^cell: joints: expected a list, got 3$"):
        check(Robot, {"model": "x", "joints": 3}, Bad, "cell")


def test_finite():
    assert finite(1.0) and finite(3) and not finite(True) and not finite(float("inf")) and not finite("1")
