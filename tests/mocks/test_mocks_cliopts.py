"""``station.mocks.cliopts``: the world an emulator command serves, and its contact device."""

from __future__ import annotations

import pytest
from station.mocks.cliopts import contact_id, world_for
from station.mocks.errors import MockError
from station.mocks.world import World


def test_the_default_world_or_the_file(tmp_path):
    w = world_for(None, "omx", 3)
    assert w.nominal.name == "omx" and w.time_mode == "realtime"  # a process on a real wire
    assert w.errors() == World.default(model="omx", seed=3).errors()  # the seed chooses the hidden errors
    f = tmp_path / "w.yaml"
    f.write_text("format: station-world/1\nunits: {length: mm, angle: deg}\nrobot: {model: omx}\n"
                 "noise: {seatting: 1}\n")
    with pytest.raises(MockError) as e:
        world_for(f, "omx", 0)
    assert str(e.value).startswith("world: ") and "seatting" in str(e.value)
    with pytest.raises(MockError, match="^world: "):
        world_for(tmp_path / "absent.yaml", "omx", 0)


def test_contact_id():
    assert contact_id(None, 200) == 200 and contact_id("7", 200) == 7
    assert contact_id("off", 200) is None and contact_id(None, None) is None and contact_id("none", 5) is None
