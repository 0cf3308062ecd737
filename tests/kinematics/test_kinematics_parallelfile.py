"""``station.kinematics.parallelfile``: a parallel robot's model file written in mm/deg and read back is the same
robot: the same actuator lengths for the same platform poses (the robot's own inverse kinematics, closed form)."""

from __future__ import annotations

import numpy as np
import pytest

from station.kinematics import ModelFileError, load_model
from station.kinematics.parallelfile import parallel_from_dict, parallel_to_dict


@pytest.mark.parametrize("name", ["hexapod", "struts2"])
def test_round_trip_in_other_units_is_the_same_robot(name):
    m = load_model(name)
    doc = parallel_to_dict(m, "mm", "deg")
    doc["format"] = "station-model/1"
    back = parallel_from_dict(doc, "rt.yaml")
    assert back.param_names == m.param_names and np.allclose(back.params, m.params, atol=1e-12)
    q = m.home_q + np.random.default_rng(0).uniform(-0.01, 0.01, (5, m.n_joints))
    T = m.fk(q)  # platform poses, then the lengths that reach them on the model read back
    legs, ok, _ = back.ik_closed(T)
    assert ok.all() and np.allclose(legs, q, atol=1e-9)


def test_bad_units_are_one_line():
    doc = parallel_to_dict(load_model("hexapod"), "mm", "deg")
    doc["units"] = {"length": "inch", "angle": "deg"}
    with pytest.raises(ModelFileError, match=r"^rt.yaml: 'units' must state length"):
        parallel_from_dict(doc, "rt.yaml")
