"""``station mock ...``: emulators and the simulated world. Every emulator's command comes from its plug in the
``station.emulators`` entry points (``station.mocks.plug``: a new bus adds its command there, not here); the
world's from ``station.mocks.world.cli``."""

from __future__ import annotations

import typer

from station.cli import COMMANDS
from station.cli.helpgroup import HelpGroup

mock_app = typer.Typer(cls=HelpGroup, no_args_is_help=True, help=COMMANDS["mock"][1])


def register(app: typer.Typer) -> None:
    from station.mocks.plug import plugs
    from station.mocks.world import cli as world_cli

    world_cli.register(mock_app)
    for plug in plugs().values():
        plug.register(mock_app)
    for group in mock_app.registered_groups:  # mock world: the same command list as every group
        group.cls = HelpGroup
    app.add_typer(mock_app, name="mock")
