"""Start ``station mock franka`` as a child process and hand out the robot URL (tests, benchmarks, scripts)::

    with FrankaEmulator("world.yaml") as emu:
        robot = open_robot(emu.url)

The child serves on a free random loopback address (libfranka's port 1337 is fixed: one robot per address,
so emulators of parallel test sessions never meet), ends with its parent and is terminated on ``close()``."""

from __future__ import annotations

import contextlib
import os
import selectors
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from station.mocks.franka.simenv import free_loopback

_CLI = "import sys; from station.cli import main; sys.argv[0] = 'station'; main()"


class FrankaEmulator:
    def __init__(self, world: str | os.PathLike, *, host: str | None = None, serial: str | None = None,
                 extra: tuple[str, ...] = (), env: dict | None = None) -> None:
        self.world = Path(world)
        self.host = host or free_loopback()
        self.serial = serial
        self.extra = tuple(extra)
        self.env = env
        self.url = ""
        self.ready_line = ""
        self.proc: subprocess.Popen | None = None
        self._log = None

    def start(self, timeout: float = 60.0) -> FrankaEmulator:
        args = ["mock", "franka", "--world", str(self.world), "--host", self.host, "--exit-with-parent",
                *(["--serial", self.serial] if self.serial else []), *self.extra]
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 - kept after close(): stderr() stays readable
        env = None if self.env is None else {**os.environ, **self.env}
        self.proc = subprocess.Popen([sys.executable, "-c", _CLI, *args], stdout=subprocess.PIPE, stderr=self._log,
                                     stdin=subprocess.DEVNULL, env=env)
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        buf = b""
        try:
            while b"\n" not in buf:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    err = self.stderr().strip()[-2000:]
                    self.close()
                    raise RuntimeError(f"`station mock franka` did not start: {err}")
                if sel.select(0.1):
                    buf += os.read(self.proc.stdout.fileno(), 4096)
        finally:
            sel.close()
        self.ready_line = buf.decode(errors="replace").splitlines()[0].strip()
        self.url = self.ready_line.rsplit("robot URL ", 1)[-1].strip()
        return self

    def stderr(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def close(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        with contextlib.suppress(OSError):
            proc.stdout.close()

    def __enter__(self) -> FrankaEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
