"""``station mock ur --host 127.0.0.N [--world FILE] [--model ur5e]``: a UR e-Series controller emulator.

Prints one line ``ur emulator ready on HOST ...; robot URL ur://...`` once every port listens (the URL works as
printed: the model, for an arm of one's own its file and ``robot_type``, and ``power_on=yes``: the emulated
controller boots with the arm powered off, as a real one, and has no teach pendant to power it on), then serves
until SIGINT/SIGTERM."""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from urllib.parse import quote

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


def robot_url(host: str, world, robot_model: str, polyscope: str) -> str:
    """The robot URL that opens this controller as printed: ``model=`` the world's built-in name or its model
    file (absolute path), chain links when the world names them, ``robot_type=`` when the model's name does not
    say which UR arm it is for (an arm of one's own), and ``power_on=yes``."""
    from station.mocks.ur.controller import UR_NAME

    from station.kinematics import builtin_names

    spec = world.spec
    name = world.nominal.name
    model = name if spec.model in builtin_names() else spec.model
    parts = [f"model={quote(str(model), safe='/')}"]
    for key in ("tip_link", "base_link"):
        if getattr(spec, key, None):
            parts.append(f"{key}={quote(str(getattr(spec, key)), safe='')}")
    if not UR_NAME.match(name):
        major = int(polyscope_major(polyscope))
        e = "e" if major >= 5 and robot_model[2:] not in ("20", "30") else ""
        parts.append(f"robot_type={robot_model}{e}")
    parts.append("power_on=yes")
    return f"ur://{host}?" + "&".join(parts)


def polyscope_major(polyscope: str) -> int:
    import re

    m = re.search(r"(\d+)\.\d+", polyscope)
    return int(m.group(1)) if m else 5


def ur(host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on (one emulator per address: "
                                "ur_rtde's RTDE port 30004 is fixed). Loopback by default."),
       world: Path | None = typer.Option(None, "--world", help="World file (station-world/1); default: a "
                                         "default world for --model."),
       model: str = typer.Option("ur5e", "--model", help="ur3e, ur5e or ur10e (when no --world)."),
       seed: int = typer.Option(0, "--seed", help="Seed of the default world (when no --world)."),
       serial: str | None = typer.Option(None, "--serial", help="Controller serial number (default: the world "
                                         "file's buses.ur.serial, else derived from the world: two worlds never "
                                         "share one)."),
       no_remote: bool = typer.Option(False, "--no-remote", help="Answer 'is in remote control' with false."),
       dump_script: Path | None = typer.Option(None, "--dump-script", help="Write the last URScript program "
                                               "received on port 30003 to this file (for inspection)."),
       verbose: bool = typer.Option(False, "--verbose", "-v", help="Log controller events to stderr."),
       exit_with_parent: bool = typer.Option(False, "--exit-with-parent", help="Stop when the process that "
                                             "started this one ends (tests: no orphan after a crash).")) -> None:
    """Emulate a Universal Robots e-Series controller (RTDE, dashboard, script port) for ur_rtde."""
    from station.mocks.ur.server import URServer

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
    where = world or f"default world for {model}"
    if w.nominal.n_joints != 6 or not all(j.revolute for j in w.nominal.joints):
        raise _fail(f"{where}: robot.model {w.nominal.name} has {w.nominal.n_joints} joints "
                    f"({', '.join(j.kind for j in w.nominal.joints)}); a UR controller drives 6 revolute joints")
    try:
        ctl = controller_for(w, serial=serial, no_remote=no_remote)
    except ValueError as e:
        raise _fail(f"{where}: {e}") from None
    url = robot_url(host, w, ctl.robot_model, ctl.polyscope)
    server = URServer(ctl, host, dump_script=str(dump_script) if dump_script else None, url=url)
    try:
        server.start()
    except OSError as e:
        raise _fail(f"cannot listen on {host}: {e}") from None
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    typer.echo(f"ur emulator ready on {host} (rtde 30004, dashboard 29999, script 30003, primary 30001, "
               f"secondary 30002) model {w.nominal.name} controller {ctl.robot_model} serial {ctl.serial} contact bit "
               f"{ctl.contact_bit}, arm {ctl.mode_name} (power_on=yes lets the station power it on); "
               f"robot URL {url}")
    sys.stdout.flush()
    parent = os.getppid()
    try:
        while not done.wait(0.5):
            if exit_with_parent and os.getppid() != parent:
                break
    finally:
        server.close()


def controller_for(w, *, serial: str | None = None, no_remote: bool = False):
    """The ``URController`` a world's ``buses.ur`` section describes (``ValueError`` naming the field)."""
    import re

    from station.mocks.ur.controller import BRAKE_RELEASE_S, POWER_ON_S, UNLOCK_DELAY, URController
    from station.mocks.ur.factory import CALIBRATION_CHOICES
    from station.mocks.ur.state import DEFAULT_CONTACT_BIT

    cfg = w.bus_config("ur")
    known = {"serial", "contact_bit", "stall_s", "drop_s", "unlock_delay_s", "remote_control", "robot_model",
             "polyscope", "calibration", "power_on_s", "brake_release_s"}
    unknown = sorted(set(cfg) - known)
    if unknown:
        raise ValueError(f"buses.ur: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    numbers = {}
    for key, kind, default, lo in (("contact_bit", int, DEFAULT_CONTACT_BIT, 0), ("stall_s", float, 1.0, 0.0),
                                   ("drop_s", float, 1.0, 0.0), ("unlock_delay_s", float, UNLOCK_DELAY, 0.0),
                                   ("power_on_s", float, POWER_ON_S, 0.0),
                                   ("brake_release_s", float, BRAKE_RELEASE_S, 0.0)):
        try:
            numbers[key] = kind(cfg.get(key, default))
            if not (numbers[key] >= lo and numbers[key] < 1e6):
                raise ValueError
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"buses.ur.{key}: {cfg.get(key)!r} is not a number >= {lo:g}") from None
    if not 0 <= numbers["contact_bit"] <= 63:
        raise ValueError(f"buses.ur.contact_bit: {numbers['contact_bit']} is not a bit 0..63")
    robot_model = cfg.get("robot_model")
    if robot_model is not None and not re.fullmatch(r"UR\d{1,2}", str(robot_model)):
        raise ValueError(f"buses.ur.robot_model: {robot_model!r} is not what a controller reports (UR3, UR5, UR10, "
                         "UR16, UR20, UR30)")
    calibration = str(cfg.get("calibration", "links"))
    if calibration not in CALIBRATION_CHOICES:
        raise ValueError(f"buses.ur.calibration: {calibration!r} is not one of {', '.join(CALIBRATION_CHOICES)}")
    from station.mocks.world.identity import default_serial

    serial = str(serial or cfg.get("serial") or default_serial(w, "ur"))
    return URController(w, serial=serial, model_name=w.nominal.name,
                        robot_model=robot_model, polyscope=cfg.get("polyscope"), calibration=calibration,
                        remote_control=not (no_remote or cfg.get("remote_control") is False), **numbers)


def register(mock_app: typer.Typer) -> None:
    mock_app.command("ur")(ur)
