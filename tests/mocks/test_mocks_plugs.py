"""Each emulator's plug (``mocks/<bus>/plug.py``) is what the ``station.emulators`` entry point of its bus names:
the launcher, ``station mock`` and ``station demo`` find it there and nowhere else."""

from __future__ import annotations

from importlib.metadata import entry_points

import pytest
from station.mocks.canopen import plug as canopen_plug
from station.mocks.dynamixel import plug as dynamixel_plug
from station.mocks.franka import plug as franka_plug
from station.mocks.plug import plugs
from station.mocks.tracker import plug as tracker_plug
from station.mocks.ur import plug as ur_plug

MODULES = {"canopen": canopen_plug, "dynamixel": dynamixel_plug, "franka": franka_plug, "tracker": tracker_plug,
           "ur": ur_plug}


@pytest.mark.parametrize("bus", sorted(MODULES))
def test_the_entry_point_of_each_bus_names_its_plug_module(bus):
    ep = {e.name: e for e in entry_points(group="station.emulators")}[bus]
    plug = MODULES[bus].PLUG
    assert ep.value == f"{MODULES[bus].__name__}:PLUG" and ep.load() is plug
    assert plug.bus == bus and plugs()[bus] is plug
    assert plug.modes, bus  # in this process, as a child process, or both
    assert plug.cli.startswith("station.mocks.") and plug.cli.endswith(".cli")
