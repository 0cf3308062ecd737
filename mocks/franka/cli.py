"""``station mock franka [--world FILE] [--host 127.0.0.N]``: a Franka Research 3 on franka-sim, the
libfranka-protocol simulator (FCI port 1337 on one loopback address), serving a station world's TRUE arm.

Writes the scene (``station.mocks.franka.scene``), then becomes the simulator process (``simhost.py`` in the
franka-sim environment: exec, so signals and ``--exit-with-parent`` reach it directly). Prints one line
``franka emulator ready on HOST ...; robot URL franka://HOST?model=fr3&serial=SN`` once it serves, then runs
until SIGINT/SIGTERM."""

from __future__ import annotations

import ipaddress
import os
import sys
import tempfile
from pathlib import Path

import typer

DEFAULT_SERIAL = "FR3-SIM-0001"


def franka(world: Path | None = typer.Option(None, "--world", help="World file (station-world/1, robot.model "
                                             "fr3); default: the default fr3 world of --seed."),
           seed: int = typer.Option(0, "--seed", help="Seed of the default world (when no --world)."),
           host: str | None = typer.Option(None, "--host", help="Loopback address to serve on (libfranka's port "
                                           "1337 is fixed: one robot per address); default: the world file's "
                                           "buses.franka.host, else a free random 127.x.y.z."),
           serial: str | None = typer.Option(None, "--serial", help="Serial number put into the printed URL (the "
                                             "FCI reports none); default: buses.franka.serial, else "
                                             f"{DEFAULT_SERIAL}."),
           sim_python: Path | None = typer.Option(None, "--sim-python", help="Interpreter of the franka-sim "
                                                  "environment (default: $STATION_FRANKA_SIM_PYTHON, else "
                                                  ".venv-franka-sim/bin/python of the source tree)."),
           scene_dir: Path | None = typer.Option(None, "--scene-dir", help="Keep the scene files (true URDF, "
                                                 "scene.json) in this folder (default: a temporary one)."),
           verbose: bool = typer.Option(False, "--verbose", "-v", help="Log the simulator's events to stderr."),
           exit_with_parent: bool = typer.Option(False, "--exit-with-parent", help="Stop when the process that "
                                                 "started this one ends (tests: no orphan after a crash).")) -> None:
    """Emulate a Franka Research 3 (franka-sim on MuJoCo) for pylibfranka, from a station world."""
    from station.mocks.cliopts import world_for
    from station.mocks.errors import MockError
    from station.mocks.franka.scene import write_scene
    from station.mocks.franka.simenv import SIMHOST, free_loopback, port_free
    from station.mocks.franka.simenv import sim_python as find_python

    python = find_python(sim_python)
    w = world_for(world, "fr3", seed)
    cfg = w.bus_config("franka")
    host = host or cfg.get("host") or free_loopback()
    try:
        addr = ipaddress.ip_address(str(host))
    except ValueError:
        raise MockError(f"--host {host!r} is not an IP address") from None
    if not addr.is_loopback:  # franka-sim binds what it is given, unauthenticated: loopback only here
        raise MockError(f"--host {host}: the Franka emulator serves on loopback addresses only (127.0.0.0/8)")
    if not port_free(str(host)):
        raise MockError(f"{host}:1337 is in use (another robot emulator there?); choose another --host")
    keep = scene_dir is not None
    folder = Path(scene_dir) if keep else Path(tempfile.mkdtemp(prefix="station-franka-"))
    scene = write_scene(w, folder, str(host))
    sn = str(serial or cfg.get("serial") or DEFAULT_SERIAL)
    url = f"franka://{host}?model=fr3&serial={sn}"
    ready = (f"franka emulator ready on {host} (FCI 1337, franka-sim) model fr3 serial {sn}; robot URL {url}")
    args = [str(python), str(SIMHOST), "--scene", str(scene), "--ready-line", ready]
    if verbose:
        args.append("--verbose")
    if exit_with_parent:
        args.append("--exit-with-parent")
    if not keep:
        args += ["--remove-dir", str(folder)]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(str(python), args)


def register(mock_app: typer.Typer) -> None:
    mock_app.command("franka")(franka)
