"""``station mock ur --host 127.0.0.N [--world FILE] [--model ur5e]``: a UR e-Series controller emulator.

Prints one line ``ur emulator ready on HOST ...`` once every port listens, then serves until SIGINT/SIGTERM."""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
import signal
import sys
import threading
from pathlib import Path

import typer


def _fail(message: str) -> typer.Exit:
    typer.echo(f"station: error: {message}", err=True)
    return typer.Exit(2)


def build(world_file: Path | None, model: str, seed: int):
    """The World the emulator serves: the file's, else a default world for ``model`` in simulated time
    driven by the controller's 2 ms cycle (so moves take as long as on a robot)."""
    from station.mocks.world import World, WorldFileError

    try:
        if world_file is not None:
            return World.from_file(world_file)
        return World.default(model=model, seed=seed, time_mode="sim")
    except (WorldFileError, OSError) as e:
        raise _fail(str(e)) from None


def ur(host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on (one emulator per address: "
                                "ur_rtde's RTDE port 30004 is fixed). Loopback by default."),
       world: Path | None = typer.Option(None, "--world", help="World file (station-world/1); default: a "
                                         "default world for --model."),
       model: str = typer.Option("ur5e", "--model", help="ur3e, ur5e or ur10e (when no --world)."),
       seed: int = typer.Option(0, "--seed", help="Seed of the default world (when no --world)."),
       serial: str | None = typer.Option(None, "--serial", help="Controller serial number (default: the world "
                                         "file's buses.ur.serial, else 20235500001)."),
       no_remote: bool = typer.Option(False, "--no-remote", help="Answer 'is in remote control' with false."),
       dump_script: Path | None = typer.Option(None, "--dump-script", help="Write the last URScript program "
                                               "received on port 30003 to this file (for inspection)."),
       verbose: bool = typer.Option(False, "--verbose", "-v", help="Log controller events to stderr."),
       exit_with_parent: bool = typer.Option(False, "--exit-with-parent", help="Stop when the process that "
                                             "started this one ends (tests: no orphan after a crash).")) -> None:
    """Emulate a Universal Robots e-Series controller (RTDE, dashboard, script port) for ur_rtde."""
    from station.mocks.ur.controller import UNLOCK_DELAY, URController
    from station.mocks.ur.server import URServer
    from station.mocks.ur.state import DEFAULT_CONTACT_BIT

    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise _fail(f"--host {host!r} is not an IP address") from None
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="ur-emulator: %(message)s")
    # the real controller is its own realtime computer, untouched by the load on the station PC: where allowed
    # (root, CAP_SYS_NICE), this process and its threads run ahead of ordinary work, so a busy host delays the
    # station (what a test measures) and not the controller's 2 ms cycle and its RTDE watchdog
    with contextlib.suppress(OSError):
        os.nice(-10)
    w = build(world, model, seed)
    cfg = w.bus_config("ur")
    numbers = {}
    for key, kind, default in (("contact_bit", int, DEFAULT_CONTACT_BIT), ("stall_s", float, 1.0),
                               ("drop_s", float, 1.0), ("unlock_delay_s", float, UNLOCK_DELAY)):
        try:
            numbers[key] = kind(cfg.get(key, default))
        except (TypeError, ValueError):
            raise _fail(f"{world}: buses.ur.{key}: {cfg.get(key)!r} is not a number") from None
    ctl = URController(w, serial=str(serial or cfg.get("serial", "20235500001")), model_name=w.nominal.name,
                       robot_model=cfg.get("robot_model"), polyscope=cfg.get("polyscope"), **numbers,
                       remote_control=not (no_remote or cfg.get("remote_control") is False))
    server = URServer(ctl, host, dump_script=str(dump_script) if dump_script else None)
    try:
        server.start()
    except OSError as e:
        raise _fail(f"cannot listen on {host}: {e}") from None
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    typer.echo(f"ur emulator ready on {host} (rtde 30004, dashboard 29999, script 30003) model {w.nominal.name} "
               f"serial {ctl.serial} contact bit {ctl.contact_bit}; robot URL ur://{host}?model={w.nominal.name}")
    sys.stdout.flush()
    parent = os.getppid()
    try:
        while not done.wait(0.5):
            if exit_with_parent and os.getppid() != parent:
                break
    finally:
        server.close()


def register(mock_app: typer.Typer) -> None:
    mock_app.command("ur")(ur)
