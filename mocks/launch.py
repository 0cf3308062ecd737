"""Start an emulator for a world and hand out the robot URL the station opens: the one launcher behind
``station demo``, the benchmarks and the tests.

    with launch("canopen", "world.yaml", serial="A6-1") as emu:
        robot = open_robot(emu.url)

- ``ur``: ``station mock ur`` as a child process (ur_rtde's constructors hold the GIL, so the controller must
  not be a thread of the process that uses ur_rtde) on a random free loopback address 127.x.y.z (ur_rtde's
  ports are fixed; random, so test sessions running side by side do not pick the same one);
- ``canopen``: the drives in this process on a python-can ``virtual`` channel of a unique name;
- ``dynamixel``: the servos in this process on a pty, or with ``process=True`` ``station mock dynamixel`` as a
  child process (a realtime demo keeps the emulator's timing out of the station's GIL).

The world is a world file (child processes need one) or, in-process, a ``World`` object. A child process
ends with its parent (``--exit-with-parent``) and is always terminated on ``close()``."""

from __future__ import annotations

import contextlib
import os
import random
import selectors
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from urllib.parse import quote

UR_PORTS = (30004, 29999, 30003)
BUSES = ("ur", "canopen", "dynamixel")
_CLI = "import sys; from station.cli import main; sys.argv[0] = 'station'; main()"


def free_loopback() -> str:
    """A random loopback address 127.A.B.C whose three UR ports are free right now."""
    rng = random.Random()
    for _ in range(200):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 255)}.{rng.randint(2, 254)}"
        if all(_port_free(host, port) for port in UR_PORTS):
            return host
    raise RuntimeError("no free loopback address for a UR emulator")


def _port_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def dashboard(host: str, command: str, timeout: float = 3.0) -> str:
    """One UR dashboard command on a fresh connection; returns the reply line."""
    with socket.create_connection((host, 29999), timeout=timeout) as s, s.makefile("rb") as f:
        f.readline()  # banner
        s.sendall((command + "\n").encode())
        return f.readline().decode().strip()


class Emulator:
    """A running emulator: ``url`` (what the station opens), ``world`` (in-process emulators: the ``World`` they
    serve), ``host`` (UR), ``port`` (Dynamixel pty path), ``emulator`` (the in-process emulator object),
    ``proc`` (a child process started with ``extra`` command-line options)."""

    def __init__(self, bus: str, world=None, *, serial: str | None = None, process: bool | None = None,
                 model: str | None = None, host: str | None = None, extra: tuple[str, ...] = ()) -> None:
        if bus not in BUSES:
            from station.mocks.errors import MockError

            raise MockError(f"no emulator for bus {bus!r}; one of {', '.join(BUSES)}")
        self.bus, self.serial, self.extra = bus, serial, tuple(extra)
        self.process = bus == "ur" if process is None else bool(process)
        if bus == "ur" and not self.process:
            raise ValueError("the UR emulator runs as a child process only (ur_rtde holds the GIL)")
        if bus == "canopen" and self.process:
            raise ValueError("launch the CANopen emulator in-process (station mock canopen serves socketcand)")
        self.world_path = None if world is None or not isinstance(world, str | os.PathLike) else Path(world)
        self.world = None if self.world_path is not None else world
        self.model = model  # a child without a world file serves the default world of this model
        self.host = host or (free_loopback() if bus == "ur" else "")
        self.url = ""
        self.port = ""  # dynamixel: the pty path
        self.ready_line = ""
        self.emulator = None
        self.proc: subprocess.Popen | None = None
        self._log = None

    # ---- start ------------------------------------------------------------------------------------------
    def start(self, timeout: float = 30.0) -> Emulator:
        try:
            if self.bus == "ur":
                self._start_ur(timeout)
            elif self.bus == "dynamixel":
                self._start_dynamixel(timeout)
            else:
                self._start_canopen()
        except BaseException:
            self.close()
            raise
        return self

    def _load_world(self):
        if self.world is None:
            from station.mocks.world import World

            if self.world_path is None and not self.model:
                raise ValueError(f"{self.bus} emulator: give a world (file or World) or a model")
            self.world = (World.from_file(self.world_path) if self.world_path is not None
                          else World.default(model=self.model))
        return self.world

    def _with_serial(self, url: str) -> str:
        return url + (f"&serial={quote(self.serial, safe='')}" if self.serial else "")

    def _world_args(self) -> list[str]:
        if self.world_path is not None:
            return ["--world", str(self.world_path)]
        if self.world is not None:
            raise ValueError("an emulator in a child process serves a world file, not a World object")
        return ["--model", self.model] if self.model else []

    def _start_ur(self, timeout: float) -> None:
        args = ["mock", "ur", "--host", self.host, *self._world_args(), "--exit-with-parent", *self.extra]
        # "ur emulator ready on HOST ...; robot URL ur://HOST?model=NAME"
        self.ready_line = self._spawn(args, timeout)[0]
        self.url = self.ready_line.rsplit("robot URL ", 1)[-1].strip()

    def _start_dynamixel(self, timeout: float) -> None:
        if self.process:
            # the pty path, then "robot URL dynamixel://PATH?model=...&ids=..."
            args = ["mock", "dynamixel", *self._world_args(), "--exit-with-parent", *self.extra]
            self.port, url_line = self._spawn(args, timeout, 2)
            self.url = self._with_serial(url_line.rsplit("robot URL ", 1)[-1].strip())
            return
        from station.mocks.dynamixel.cli import emulator_for

        self.emulator = emulator_for(self._load_world())  # the world's buses.dynamixel settings, as the CLI
        self.port = self.emulator.start().path
        self.url = self._with_serial(self.emulator.url)

    def _start_canopen(self) -> None:
        from station.mocks.canopen.emulator import CanopenEmulator

        world = self._load_world()
        channel = f"emu{uuid.uuid4().hex[:10]}"
        self.emulator = CanopenEmulator(world, "virtual", channel).start()
        nodes = ",".join(str(n) for n in self.emulator.nodes)
        self.url = self._with_serial(f"canopen+virtual://{channel}?nodes={nodes}&model={world.nominal.name}")

    def _spawn(self, args: list[str], timeout: float, lines: int = 1) -> list[str]:
        """Start ``station ARGS`` and return its first ``lines`` stdout lines (the emulator's ready lines)."""
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 - kept after close(): stderr() stays readable
        self.proc = subprocess.Popen([sys.executable, "-c", _CLI, *args], stdout=subprocess.PIPE,
                                     stderr=self._log, stdin=subprocess.DEVNULL)
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        buf = b""
        try:
            while buf.count(b"\n") < lines:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"emulator `station {' '.join(args[:2])}` did not start: "
                                       f"{self.stderr().strip()[-2000:]}")
                if sel.select(0.1):
                    buf += os.read(self.proc.stdout.fileno(), 4096)
        finally:
            sel.close()
        return [line.strip() for line in buf.decode(errors="replace").splitlines()[:lines]]

    # ---- while running ----------------------------------------------------------------------------------
    def stderr(self) -> str:
        """What the child process wrote to stderr so far."""
        if self._log is None:
            return ""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def dashboard(self, command: str) -> str:
        return dashboard(self.host, command)

    # ---- end --------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self.emulator is not None:
            emu, self.emulator = self.emulator, None
            emu.stop()
        if self.proc is not None:
            proc, self.proc = self.proc, None
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=10)
            with contextlib.suppress(OSError):
                proc.stdout.close()

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def launch(bus: str, world=None, **kw) -> Emulator:
    """An emulator for ``world`` on ``bus`` (not started yet: ``with launch(...) as emu`` or ``.start()``)."""
    return Emulator(bus, world, **kw)
