"""``station mock ...``: emulators and the simulated world. Each bus's emulator package provides
``station.mocks.<bus>.cli.register(mock_app)``; the world provides ``station.mocks.world.cli``."""

from __future__ import annotations

import importlib

import typer

from station.cli import COMMANDS
from station.cli.helpgroup import HelpGroup

mock_app = typer.Typer(cls=HelpGroup, no_args_is_help=True, help=COMMANDS["mock"][1])

PROVIDERS = ("station.mocks.world.cli", "station.mocks.dynamixel.cli", "station.mocks.canopen.cli",
             "station.mocks.ur.cli", "station.mocks.tracker.cli", "station.mocks.franka.cli")


def register(app: typer.Typer) -> None:
    for name in PROVIDERS:
        importlib.import_module(name).register(mock_app)
    for group in mock_app.registered_groups:  # mock world: the same command list as every group
        group.cls = HelpGroup
    app.add_typer(mock_app, name="mock")
