"""``station mock tracker``: the emulated laser tracker as a process (protocol: ``station.mocks.tracker.server``).

The tracker measures the world's robot, so it must live where the world's joint state lives: with
``--canopen`` the same process also serves the world's CiA 402 drives behind a socketcand hub (as
``station mock canopen`` does). Without it the robot stands at the world's start pose (protocol checks, a
CSV-import rehearsal). Prints one line per server (flushed), then runs until SIGTERM/SIGINT:

    tracker 127.0.0.1:PORT url tcp://127.0.0.1:PORT serial LT-EMU-0001
    socketcand 127.0.0.1:PORT channel can0 url canopen+socketcand://...      (with --canopen)"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

import typer
from station.mocks.errors import MockError


def _world(world_file: Path | None, model: str, seed: int):
    from station.mocks.world import World, WorldFileError

    try:
        return World.from_file(world_file) if world_file else World.default(model=model, seed=seed,
                                                                             time_mode="realtime")
    except (WorldFileError, ValueError, OSError) as e:
        raise MockError(f"world: {e}") from None


def register(mock_app: typer.Typer) -> None:
    @mock_app.command("tracker")
    def tracker(
        world: Path = typer.Option(None, "--world", help="World file (docs/world.md; buses.tracker places the "
                                                         "instrument, docs/map.md); default: built-in world"),
        model: str = typer.Option("hexapod", "--model", help="Model of the default world"),
        seed: int = typer.Option(0, "--seed", help="Seed of the default world's hidden errors and of the noise"),
        host: str = typer.Option("127.0.0.1", "--host", help="Loopback address the tracker listens on"),
        port: int = typer.Option(0, "--port", help="TCP port of the tracker (0: any free port)"),
        canopen: bool = typer.Option(False, "--canopen", help="Also serve the world's CiA 402 drives (socketcand)"),
        can_port: int = typer.Option(0, "--can-port", help="With --canopen: TCP port of the socketcand hub"),
        channel: str = typer.Option("can0", "--channel", help="With --canopen: bus name clients open"),
    ) -> None:
        """Emulated laser tracker (6-DoF probe on the tool, 15 um + 6 um/m); prints its tcp:// URL."""
        import ipaddress

        from station.mocks.tracker.config import tracker_config
        from station.mocks.tracker.server import TrackerServer

        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = host == "localhost"
        if not loopback:
            raise MockError(f"--host {host}: the emulated tracker has no authentication; it listens on loopback only")
        w = _world(world, model, seed)
        cfg = tracker_config(w.bus_config("tracker"))
        done = threading.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: done.set())
        try:
            server = TrackerServer(w, cfg, host=host, port=port, seed=seed).start()
        except OSError as e:
            raise MockError(f"tracker: cannot listen on {host}:{port} ({e.strerror or e})") from None
        emu = hub = None
        try:
            sys.stdout.write(f"tracker {server.host}:{server.port} url {server.url} serial {cfg.serial}\n")
            if canopen:
                from station.mocks.canopen.emulator import CanopenEmulator
                from station.mocks.canopen.hub import SocketcandHub

                internal = f"station-tracker-can-{os.getpid()}"
                try:
                    emu = CanopenEmulator(w, interface="virtual", channel=internal).start()
                except ValueError as e:
                    raise MockError(str(e)) from None
                hub = SocketcandHub(internal, host=host, port=can_port, name=channel)
                try:
                    hub.start()
                except OSError as e:
                    raise MockError(str(e)) from None
                ids = ",".join(str(n) for n in emu.nodes)
                sys.stdout.write(f"socketcand {host}:{hub.port} channel {channel} url canopen+socketcand://{host}:"
                                 f"{hub.port}?channel={channel}&nodes={ids}&model={w.nominal.name}\n")
            sys.stdout.flush()
            while not done.wait(0.5):
                pass
        finally:
            if hub is not None:
                hub.stop()
            if emu is not None:
                emu.stop()
            server.stop()
