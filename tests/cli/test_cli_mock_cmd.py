"""``station.cli.mock_cmd`` and the emulator packages' command modules it gathers through the
``station.emulators`` plugs: every plug registers the ``station mock`` command of its bus, and the installed
command lists them all."""

from __future__ import annotations

import typer
from clirunner import station_main
from station.mocks.canopen import cli as canopen_cli
from station.mocks.dynamixel import cli as dynamixel_cli
from station.mocks.franka import cli as franka_cli
from station.mocks.plug import plugs
from station.mocks.tracker import cli as tracker_cli
from station.mocks.ur import cli as ur_cli
from station.mocks.world import cli as world_cli

import station.cli.mock_cmd  # noqa: F401 - the module under test (registers what the plugs name)

MODULES = {"world": world_cli, "dynamixel": dynamixel_cli, "canopen": canopen_cli, "ur": ur_cli,
           "tracker": tracker_cli, "franka": franka_cli}


def test_each_provider_registers_its_bus_and_station_mock_lists_them():
    assert {p.cli for p in plugs().values()} == {m.__name__ for b, m in MODULES.items() if b != "world"}
    for bus, module in MODULES.items():
        app = typer.Typer()
        module.register(app)
        names = [c.name for c in app.registered_commands] + [g.name for g in app.registered_groups]
        assert names == [bus], (module.__name__, names)
    r = station_main("mock", "--help", columns=120)
    assert r.code == 0, r.err
    listed = {line.split()[0] for line in r.out.splitlines() if line.startswith("  ") and line.split()}
    assert set(MODULES) <= listed
