"""Run ``station mock ur`` as a child process (tests, benchmarks, demos).

ur_rtde's constructors block without releasing the GIL, so the emulator must never run as a thread of the
process that uses ur_rtde. One emulator per loopback address: ur_rtde's port 30004 is fixed."""

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

PORTS = (30004, 29999, 30003)
_CLI = "import sys; from station.cli import main; sys.argv[0] = 'station'; main()"


def _ports_free(host: str) -> bool:
    for port in PORTS:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            s.bind((host, port))
        except OSError:
            return False
        finally:
            s.close()
    return True


def free_loopback() -> str:
    """A random loopback address 127.A.B.C whose three UR ports are free right now. Random, so that test
    sessions running side by side (other engineers, CI shards) do not pick the same address."""
    rng = random.Random()
    for _ in range(200):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 255)}.{rng.randint(2, 254)}"
        if _ports_free(host):
            return host
    raise RuntimeError("no free loopback address for a UR emulator")


def dashboard(host: str, command: str, timeout: float = 3.0) -> str:
    """One dashboard command on a fresh connection; returns the reply line."""
    with socket.create_connection((host, 29999), timeout=timeout) as s, s.makefile("rb") as f:
        f.readline()  # banner
        s.sendall((command + "\n").encode())
        return f.readline().decode().strip()


class EmulatorProcess:
    """``with EmulatorProcess(world="w.yaml") as emu: ... emu.host``; always terminated on exit."""

    def __init__(self, host: str | None = None, world: str | os.PathLike | None = None, model: str = "ur5e",
                 extra: tuple[str, ...] = ()) -> None:
        self.host = host or free_loopback()
        self.args = ["mock", "ur", "--host", self.host]
        if world is not None:
            self.args += ["--world", str(world)]
        else:
            self.args += ["--model", model]
        self.args += ["--exit-with-parent", *extra]
        self.proc: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 - lives as long as this object; closed in stop()
        self.ready_line = ""

    def start(self, timeout: float = 20.0) -> EmulatorProcess:
        self.proc = subprocess.Popen([sys.executable, "-c", _CLI, *self.args], stdout=subprocess.PIPE,
                                     stderr=self._log, stdin=subprocess.DEVNULL)
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        buf = b""
        try:
            while b"\n" not in buf:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(f"UR emulator on {self.host} did not start: {self.stderr()[-2000:]}")
                if sel.select(0.1):
                    chunk = os.read(self.proc.stdout.fileno(), 4096)
                    if not chunk:
                        continue
                    buf += chunk
        finally:
            sel.close()
        self.ready_line = buf.decode(errors="replace").strip()
        return self

    def stderr(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def dashboard(self, command: str) -> str:
        return dashboard(self.host, command)

    def stop(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        with contextlib.suppress(OSError):
            self.proc.stdout.close()
        self.proc = None

    def __enter__(self) -> EmulatorProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
