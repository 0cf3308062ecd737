"""Robot URLs take a URDF model with ``tip_link=``/``base_link=`` on every driver: the chain the URL
names is the one the driver loads; a URDF with several chain ends and no tip is one line naming the candidates.
The 7-DOF arm's hand has two fingers besides the ball; the reference is the URDF reader (checked against yourdfpy
in test_urdf.py)."""

import numpy as np
import pytest
from urdf_robots import arm7_urdf, write

from station.kinematics import load_model
from station.robot import registry
from station.robot.errors import ConfigError
from station.robot.url import parse_url


@pytest.mark.parametrize("scheme,rest", [("dynamixel", "/dev/null?ids=1-7"), ("canopen+virtual", "x?nodes=1-7"),
                                         ("ur", "127.0.0.1?")])
def test_every_driver_loads_the_named_chain(tmp_path, scheme, rest):
    path = write(tmp_path, "arm7", arm7_urdf())
    cls = registry.driver_class(scheme)
    url = parse_url(f"{scheme}://{rest}&model={path}&tip_link=ball")
    o = cls.options.parse(url)
    m = cls.load_url_model(url, o["model"], o["tip_link"], o["base_link"])
    ref = load_model(path, tip_link="ball")  # the URDF reader itself, tested against yourdfpy in test_urdf.py
    q = np.linspace(-0.4, 0.5, m.n_joints)
    assert m.n_joints == 7 and np.allclose(m.fk(q), ref.fk(q), atol=1e-12)
    url = parse_url(f"{scheme}://{rest}&model={path}")
    o = cls.options.parse(url)
    with pytest.raises(ConfigError) as e:
        cls.load_url_model(url, o["model"], o["tip_link"], o["base_link"])
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("robot URL") and "finger_left" in msg and "tip_link" in msg

