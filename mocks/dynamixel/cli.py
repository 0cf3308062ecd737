"""``station mock dynamixel``: the Dynamixel bus emulator as a process; prints the pty path and runs
until SIGTERM/SIGINT."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
from pathlib import Path
from urllib.parse import quote

import typer
from station.mocks.cliopts import SEED, WORLD
from station.mocks.errors import MockError


def _load_eeprom(path: Path | None) -> dict[int, bytes]:
    if path is None or not path.exists():
        return {}
    try:
        doc = json.loads(path.read_text())
        return {int(k): bytes.fromhex(v) for k, v in doc["eeprom"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise MockError(f"{path}: not a dynamixel EEPROM file ({e})") from None


def _save_eeprom(path: Path, images: dict[int, bytes]) -> None:
    doc = {"format": "station-dxl-eeprom/1", "note": "EEPROM bytes 0..63 of each emulated device by id, hex",
           "eeprom": {str(k): v.hex() for k, v in sorted(images.items())}}
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    tmp.replace(path)


def build_emulator(world_file: Path | None, model: str, ids: str | None, baud: int | None, wire_timing: bool,
                   return_delay: int | None, contact_id: str | None, servo: str | None, eeprom: Path | None,
                   seed: int = 0):
    from station.mocks.cliopts import world_for

    return emulator_for(world_for(world_file, model, seed), ids, baud, wire_timing, return_delay, contact_id, servo,
                        _load_eeprom(eeprom))


def emulator_for(world, ids: str | None = None, baud: int | None = None, wire_timing: bool = False,
                 return_delay: int | None = None, contact_id: str | None = None, servo: str | None = None,
                 eeprom: dict[int, bytes] | None = None):
    """The emulator for ``world``: options given here win over the world file's ``buses.dynamixel`` section,
    which wins over the defaults (ids 1..n, contact sensor id 200, XM430, 1 Mbaud, firmware 46 with Fast Sync
    Read, Status Return Level 2)."""
    from station.mocks import cliopts
    from station.mocks.dynamixel.emulator import DEFAULT_CONTACT_ID, DynamixelEmulator
    from station.mocks.ids import parse_id_list

    cfg = world.bus_config("dynamixel")
    try:
        id_list = parse_id_list(ids) if ids else (parse_id_list(cfg["ids"]) if cfg.get("ids") else None)
    except (ValueError, TypeError):
        raise MockError(f"bad servo id list {ids or cfg.get('ids')!r}: expected e.g. 11-14 or 11,12,13,14") from None
    c = cliopts.contact_id(contact_id, cfg.get("contact_id", DEFAULT_CONTACT_ID))
    fast = cfg.get("fast_sync_read", True)
    if not isinstance(fast, bool):
        raise MockError(f"buses.dynamixel.fast_sync_read: {fast!r} is not true or false")
    for key in ("firmware", "status_return_level"):
        if cfg.get(key) is not None and (isinstance(cfg[key], bool) or not isinstance(cfg[key], int)):
            raise MockError(f"buses.dynamixel.{key}: {cfg[key]!r} is not an integer")
    try:
        return DynamixelEmulator(world, id_list, servo=servo or cfg.get("servo", "xm430"),
                                 baud=int(baud or cfg.get("baud", 1_000_000)),
                                 return_delay=int(return_delay if return_delay is not None
                                                  else cfg.get("return_delay", 0)),
                                 wire_timing=wire_timing or bool(cfg.get("wire_timing", False)),
                                 contact_id=c, eeprom=eeprom or {}, fast_sync_read=fast,
                                 firmware=None if cfg.get("firmware") is None else int(cfg["firmware"]),
                                 status_return_level=None if cfg.get("status_return_level") is None
                                 else int(cfg["status_return_level"]))
    except ValueError as e:
        raise MockError(str(e)) from None


def arm_serial(world) -> str:
    """``buses.dynamixel.serial``, else one derived from the world (servos report none; records tell arms apart
    by it)."""
    from station.mocks.world.identity import default_serial

    return str(world.bus_config("dynamixel").get("serial") or default_serial(world, "dynamixel"))


def register(mock_app: typer.Typer) -> None:
    @mock_app.command("dynamixel")
    def dynamixel(
        world: Path = WORLD,
        model: str = typer.Option("omx", "--model", help="Model of the default world"),
        seed: int = SEED,
        ids: str = typer.Option(None, "--ids", help="Servo ids in joint order, e.g. 11-14 (default 1..n)"),
        baud: int = typer.Option(None, "--baud", help="Baud rate (default 1000000)"),
        wire_timing: bool = typer.Option(False, "--wire-timing", help="Answer after real wire time"),
        return_delay: int = typer.Option(None, "--return-delay", help="Return delay time, units of 2 us"),
        contact: str = typer.Option(None, "--contact-id", help="Contact sensor id (default 200, 'none': off)"),
        servo: str = typer.Option(None, "--servo", help="Servo model: xm430 (default) or xl430"),
        eeprom: Path = typer.Option(None, "--eeprom", help="EEPROM file: loaded at start, saved at exit"),
        serial: str = typer.Option(None, "--serial", help="The arm's serial number in the printed robot URL "
                                   "(default: the world file's buses.dynamixel.serial, else derived from the world: "
                                   "two worlds never share one)"),
        exit_with_parent: bool = typer.Option(False, "--exit-with-parent", help="Stop when the process that "
                                              "started this one ends (tests: no orphan after a crash)."),
    ) -> None:
        """Emulated Dynamixel servos (Protocol 2.0) on a pseudo-terminal; prints the pty path, then the robot URL."""
        emu = build_emulator(world, model, ids, baud, wire_timing, return_delay, contact, servo, eeprom, seed)
        serial = serial or arm_serial(emu.world)
        done = threading.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: done.set())
        emu.start()
        parent = os.getppid()
        try:
            sys.stdout.write(f"{emu.path}\nrobot URL {emu.url}&serial={quote(serial, safe='')}\n")
            sys.stdout.flush()
            while not done.wait(0.5):
                if exit_with_parent and os.getppid() != parent:
                    break
        finally:
            emu.stop()
            if eeprom is not None:
                _save_eeprom(eeprom, emu.eeprom())
