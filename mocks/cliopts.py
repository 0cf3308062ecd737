"""What the emulator commands (``station mock dynamixel|canopen``) share: the options choosing the world they
serve, that world, and the id of the device with the contact input. Errors are ``MockError`` (one line, exit 2)."""

from __future__ import annotations

from pathlib import Path

import typer
from station.mocks.errors import MockError

WORLD = typer.Option(None, "--world", help="World file (docs/world.md); default: built-in world")
SEED = typer.Option(0, "--seed", help="Seed of the default world's hidden errors")


def world_for(world_file: Path | None, model: str, seed: int):
    """The world file's World, else the default world of ``model`` with hidden errors from ``seed``, in real time
    (a process on a real wire)."""
    from station.mocks.world import World, WorldFileError

    try:
        return World.from_file(world_file) if world_file else World.default(model=model, seed=seed,
                                                                            time_mode="realtime")
    except (WorldFileError, ValueError, OSError) as e:
        raise MockError(f"world: {e}") from None


def contact_id(given: str | int | None, configured) -> int | None:
    """The contact device's id: the option's, else the world file's; ``none``/``off`` (or empty): no contact."""
    c = given if given is not None else configured
    return None if c is None or str(c).lower() in ("none", "off", "") else int(c)
