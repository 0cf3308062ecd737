"""``station mock canopen``: emulated CiA 402 drives behind a socketcand hub, as a process.

Prints one line (flushed) with the address and channel to give python-can and the robot URL, then runs
until SIGTERM/SIGINT."""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

import typer
from station.mocks.cliopts import SEED, WORLD
from station.mocks.errors import MockError


def build(world_file: Path | None, model: str, seed: int, nodes: str | None, contact: str | None,
          store: Path | None, channel: str):
    from station.mocks.canopen.emulator import CanopenEmulator
    from station.mocks.cliopts import contact_id, world_for
    from station.mocks.ids import parse_id_list

    world = world_for(world_file, model, seed)
    cfg = world.bus_config("canopen")
    try:
        node_list = parse_id_list(nodes) if nodes else None
    except ValueError:
        raise MockError(f"bad node id list {nodes!r}: expected e.g. 1-6 or 1,2,4") from None
    c = contact_id(contact, cfg.get("contact_node", -1))
    try:
        return CanopenEmulator(world, interface="virtual", channel=channel, nodes=node_list, contact_node=c,
                               store_path=store)
    except ValueError as e:
        raise MockError(str(e)) from None


def register(mock_app: typer.Typer) -> None:
    @mock_app.command("canopen")
    def canopen(
        nodes: str = typer.Option(None, "--nodes", help="Node ids in joint order, e.g. 1-6 (default 1..n)"),
        world: Path = WORLD,
        model: str = typer.Option("arm6", "--model", help="Model of the default world"),
        seed: int = SEED,
        host: str = typer.Option("127.0.0.1", "--host", help="Address the socketcand hub listens on"),
        port: int = typer.Option(29536, "--port", help="TCP port of the socketcand hub (0: any free port)"),
        bus: str = typer.Option("can0", "--channel", help="Bus name clients open (python-can channel)"),
        contact: str = typer.Option(None, "--contact-node", help="Node with the contact input (default: last; "
                                                                 "'none': no contact input)"),
        store: Path = typer.Option(None, "--store", help="JSON file keeping parameters saved with 0x1010 "
                                                         "across emulator restarts"),
        exit_with_parent: bool = typer.Option(False, "--exit-with-parent", help="Stop when the process that "
                                              "started this one ends (tests: no orphan after a crash)."),
        error_mask: str = typer.Option("0", "--error-mask", help="CAN error classes the hub forwards (hex, as "
                                       "socketcand -e; default 0: none, as socketcand)"),
    ) -> None:
        """Emulated CiA 402 servo drives behind a socketcand hub; prints host:port, channel and robot URL."""
        from station.mocks.canopen.hub import SocketcandHub

        try:
            mask = int(error_mask, 16)
        except ValueError:
            raise MockError(f"--error-mask {error_mask!r}: expected a hexadecimal mask such as 0x1FFFFFFF") from None
        internal = f"station-canopen-{os.getpid()}"
        emu = build(world, model, seed, nodes, contact, store, internal)
        done = threading.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: done.set())
        emu.start()
        hub = SocketcandHub(internal, host=host, port=port, name=bus, error_mask=mask)
        try:
            hub.start()
        except OSError as e:
            emu.stop()
            raise MockError(str(e)) from None
        try:
            ids = ",".join(str(n) for n in emu.nodes)
            url = (f"canopen+socketcand://{host}:{hub.port}?channel={bus}&nodes={ids}"
                   f"&model={emu.world.nominal.name}")
            sys.stdout.write(f"socketcand {host}:{hub.port} channel {bus} url {url}\n")
            sys.stdout.flush()
            parent = os.getppid()
            while not done.wait(0.5):
                if exit_with_parent and os.getppid() != parent:
                    break
        finally:
            hub.stop()
            emu.stop()
