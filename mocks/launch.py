"""Start an emulator for a world and hand out the URL the station opens: the one launcher behind
``station demo``, the benchmarks and the tests.

    with launch("canopen", "world.yaml", serial="A6-1") as emu:
        robot = open_robot(emu.url)

Which emulators exist, and how each runs, is not written here: every ``station.emulators`` entry point names a
plug (``station.mocks.plug``) saying whether its emulator runs in this process (``process=False``: the World
object is shared, ``emu.world``, ``emu.emulator``), as ``station mock BUS`` in a child process (``process=True``:
the controller keeps its own interpreter, e.g. ur_rtde holds the GIL; ``emu.proc``), or either (the first of
its modes is the default). The world is a world file (a child process needs one) or, in-process, a ``World``.
A child ends with its parent (``--exit-with-parent``) and is always terminated by ``stop()``/``close()``."""

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
from pathlib import Path
from urllib.parse import quote

from station.mocks.emulator import EmulatorBase
from station.mocks.errors import MockError
from station.mocks.plug import CHILD, IN_PROCESS, find, plugs

UR_PORTS = (30004, 29999, 30003)
_CLI = "import sys; from station.cli import main; sys.argv[0] = 'station'; main()"


def __getattr__(name: str):
    if name == "BUSES":  # the robot buses registered now (entry points)
        return tuple(plugs("robot"))
    raise AttributeError(name)


def free_loopback(ports=UR_PORTS) -> str:
    """A random loopback address 127.A.B.C whose ``ports`` are free right now (side-by-side emulators with fixed
    ports never meet)."""
    rng = random.Random()
    for _ in range(200):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 255)}.{rng.randint(2, 254)}"
        if all(_port_free(host, port) for port in ports):
            return host
    raise MockError("no free loopback address for an emulator")


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


class Emulator(EmulatorBase):
    """A launched emulator: ``url`` (what the station opens), ``world`` (in-process: the ``World`` it serves;
    None for a child), ``world_path``, ``serial``, ``host`` (a child's own loopback address, where its plug needs
    one), ``port`` (Dynamixel: the pty path), ``emulator`` (the in-process emulator object), ``proc`` (the child
    process, started with ``extra`` command-line options and ``env`` added to its environment), ``plug``."""

    def __init__(self, bus: str, world=None, *, serial: str | None = None, process: bool | None = None,
                 model: str | None = None, host: str | None = None, extra: tuple[str, ...] = (),
                 env: dict | None = None, timeout: float = 60.0) -> None:
        self.plug = find(bus)
        self.bus, self.serial, self.extra, self.env, self.timeout = bus, serial, tuple(extra), env, timeout
        mode = self.plug.modes[0] if process is None else (CHILD if process else IN_PROCESS)
        if mode not in self.plug.modes:
            only = "a child process" if self.plug.modes == (CHILD,) else "this process"
            raise ValueError(f"the {bus} emulator runs in {only} only"
                             + (" (ur_rtde holds the GIL)" if bus == "ur" else ""))
        self.process = mode == CHILD
        self.world_path = None if world is None or not isinstance(world, str | os.PathLike) else Path(world)
        self.world = None if self.world_path is not None else world
        self.model = model  # a child without a world file serves the default world of this model
        self.host = host or ""
        self._url = ""
        self.port = ""  # dynamixel: the pty path
        self.ready_line = ""
        self.emulator: EmulatorBase | None = None
        self.proc: subprocess.Popen | None = None
        self._log = None

    @property
    def url(self) -> str:
        return self._url

    @url.setter
    def url(self, value: str) -> None:  # a test may add options to what the station opens
        self._url = value

    # ---- start ------------------------------------------------------------------------------------------
    def _startup(self) -> None:
        if self.process:
            self._start_child()
        else:
            self._start_in_process()

    def _load_world(self):
        if self.world is None:
            from station.mocks.world import World

            model = self.model or self.plug.default_model
            if self.world_path is None and not model:
                raise ValueError(f"{self.bus} emulator: give a world (file or World) or a model")
            self.world = (World.from_file(self.world_path) if self.world_path is not None
                          else World.default(model=model))
        return self.world

    def _with_serial(self, url: str) -> str:
        if not self.serial or not self.plug.serial_in_url(self):
            return url
        return url + ("&" if "?" in url else "?") + f"serial={quote(self.serial, safe='')}"

    def _start_in_process(self) -> None:
        self.emulator = self.plug.build(self._load_world()).start()
        self.port = getattr(self.emulator, "path", "") or ""
        self._url = self._with_serial(self.emulator.url)

    def _world_args(self) -> list[str]:
        if self.world_path is not None:
            return ["--world", str(self.world_path)]
        if self.world is not None:
            raise ValueError("an emulator in a child process serves a world file, not a World object")
        return ["--model", self.model] if self.model else []

    def _start_child(self) -> None:
        args = ["mock", self.bus, *self._world_args(), *self.plug.child_args(self), "--exit-with-parent",
                *self.extra]
        lines = self._spawn(args, self.timeout, self.plug.ready_lines)
        self.ready_line = lines[-1]
        self._url = self._with_serial(self.plug.child_url(self, lines))

    def _spawn(self, args: list[str], timeout: float, lines: int = 1) -> list[str]:
        """Start ``station ARGS`` and return its first ``lines`` stdout lines (the emulator's ready lines)."""
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 - kept after close(): stderr() stays readable
        env = None if self.env is None else {**os.environ, **self.env}
        self.proc = subprocess.Popen([sys.executable, "-c", _CLI, *args], stdout=subprocess.PIPE,
                                     stderr=self._log, stdin=subprocess.DEVNULL, env=env)
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

    def dashboard(self, command: str, timeout: float = 3.0) -> str:
        """A UR controller's dashboard command (the emulator's own commands included)."""
        return dashboard(self.host, command, timeout)

    def power_cycle(self) -> None:
        """The emulated device off and on (its non-volatile store kept, volatile state lost); the URL stays."""
        if self.emulator is not None:
            self.emulator.power_cycle()
        elif self.proc is not None:
            self.plug.power_cycle_child(self)
        else:
            raise MockError(f"the {self.bus} emulator is not running")

    # ---- end --------------------------------------------------------------------------------------------
    def _shutdown(self) -> None:
        if self.emulator is not None:
            emu, self.emulator = self.emulator, None
            emu.stop()
        if self.proc is not None:
            proc, self.proc = self.proc, None
            end_child(proc)


def end_child(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """Terminate a child emulator (killed if it does not end within ``timeout``) and close its pipe."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
    with contextlib.suppress(OSError):
        proc.stdout.close()


def launch(bus: str, world=None, **kw) -> Emulator:
    """An emulator for ``world`` on ``bus`` (not started yet: ``with launch(...) as emu`` or ``.start()``)."""
    return Emulator(bus, world, **kw)
