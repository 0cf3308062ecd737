"""The emulated laser tracker: a line protocol over TCP on loopback (docs/map.md, "Tracker protocol").

Each request is one ASCII line ending in LF; each answer is one line:

- ``ID`` -> ``OK station-tracker/1 SERIAL model=MODEL sigma0_m=S0 sigma_per_m=S1``
- ``MEASURE`` -> ``OK x y z rx ry rz t``: the tool frame (6-DoF probe: rigid fit of its reflectors) in the
  instrument's OWN frame, position in m, rotation vector in rad, ``t`` the instrument clock in s; or
  ``ERR moving: ...`` while the target moves (a tracker does not give a stationary reading of a moving probe).
- ``QUIT`` -> ``OK bye``, then the connection closes. Anything else -> ``ERR unknown command ...``.

The truth is the world's true tool pose (``World.tip_pose_true()``), measured with
``station.mocks.world.tracker.measure_poses`` (15 um + 6 um/m per reflector and axis, 1 sigma). Faults
(``world.faults``, device ``"tracker"``): ``timeout`` swallows one request (no answer), ``disconnect`` closes
the connection, ``device_fault`` answers ``ERR beam: ...`` (beam interrupted)."""

from __future__ import annotations

import contextlib
import socket
import socketserver
import threading
import time

import numpy as np
from station.mocks.emulator import EmulatorBase
from station.mocks.tracker.config import TrackerConfig
from station.mocks.world.tracker import SIGMA_0, SIGMA_PER_M, measure_poses

from station.kinematics import se3

PROTOCOL = "station-tracker/1"
DEVICE = "tracker"
MAX_LINE = 256


class TrackerServer(EmulatorBase):
    """A tracker serving ``world`` on ``host:port`` (port 0: any free port) from a thread of this process (an
    ``EmulatorBase``: ``start()`` returns it, ``stop()`` idempotent, ``url``, ``power_cycle()``). The port is bound
    at construction (``port`` known at once); a tracker never started is only an instrument model (``measure()``)."""

    def __init__(self, world, config: TrackerConfig, host: str = "127.0.0.1", port: int = 0, seed: int = 0) -> None:
        self.world, self.config = world, config
        self.rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self.measurements = 0
        self._conns: set[socket.socket] = set()
        self._server = self._bind(host, port)
        self.host, self.port = self._server.server_address[:2]
        self._thread: threading.Thread | None = None

    def _bind(self, host: str, port: int) -> socketserver.ThreadingTCPServer:
        outer = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                with outer._lock:
                    outer._conns.add(self.connection)
                try:
                    outer._serve(self.rfile, self.wfile, self.connection)
                finally:
                    with outer._lock:
                        outer._conns.discard(self.connection)

        class Server(socketserver.ThreadingTCPServer):
            daemon_threads = True
            allow_reuse_address = True

        return Server((host, port), Handler)

    @property
    def url(self) -> str:
        return f"tcp://{self.host}:{self.port}"

    def _startup(self) -> None:
        self._thread = threading.Thread(target=self._server.serve_forever, name="tracker", daemon=True)
        self._thread.start()

    def _shutdown(self) -> None:
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join(timeout=5)
            self._thread = None
        self._server.server_close()
        self._drop_connections()

    def _drop_connections(self) -> None:
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)

    def power_cycle(self) -> None:
        """The instrument off and on: every connection drops, it listens again on the same port (its clock
        restarts; its placement, ``config``, is its set-up and stays)."""
        self._shutdown()
        self._t0 = time.monotonic()
        self._server = self._bind(self.host, self.port)
        if self.started:
            self._startup()

    # ---- one connection ------------------------------------------------------------------------------
    def _serve(self, rfile, wfile, conn: socket.socket) -> None:
        while True:
            line = rfile.readline(MAX_LINE + 1)
            if not line:
                return
            faults = getattr(self.world, "faults", None)
            if faults is not None:
                if faults.take("disconnect", DEVICE):
                    with contextlib.suppress(OSError):
                        conn.shutdown(socket.SHUT_RDWR)
                    return
                if faults.take("timeout", DEVICE):
                    continue
            if len(line) > MAX_LINE:
                reply, done = f"ERR line longer than {MAX_LINE} bytes", True
            else:
                reply, done = self.answer(line.decode("ascii", errors="replace").strip())
            try:
                wfile.write((reply + "\n").encode("ascii"))
                wfile.flush()
            except OSError:
                return
            if done:
                return

    def answer(self, request: str) -> tuple[str, bool]:
        """The reply line to one request, and whether the connection ends after it."""
        cmd = request.upper()
        if cmd == "ID":
            return (f"OK {PROTOCOL} {self.config.serial} model={self.config.model} sigma0_m={SIGMA_0:g} "
                    f"sigma_per_m={SIGMA_PER_M:g}"), False
        if cmd == "QUIT":
            return "OK bye", True
        if cmd == "MEASURE":
            faults = getattr(self.world, "faults", None)
            if faults is not None and faults.take("device_fault", DEVICE):
                return "ERR beam: beam interrupted, reacquire the target", False
            if self.world.is_moving():
                return "ERR moving: the target is moving; measure when it stands still", False
            try:
                return "OK " + " ".join(f"{v:.9g}" for v in self.measure()), False
            except ValueError as e:  # the world cannot place the tool (e.g. a parallel robot that does not assemble)
                return f"ERR target: no reflector in view ({str(e)[:80]})", False
        return f"ERR unknown command {request[:40]!r} (ID, MEASURE, QUIT)", False

    def measure(self) -> np.ndarray:
        """One 6-DoF reading: x, y, z (m), rx, ry, rz (rotation vector, rad) in the instrument frame, t (s)."""
        T = self.world.tip_pose_true()
        with self._lock:
            if self.config.noise:
                M = measure_poses(T, self.config.reflectors, self.config.tracker_in_base, self.rng)[0]
            else:
                M = se3.invert(self.config.tracker_in_base) @ np.asarray(T, float).reshape(4, 4)
            self.measurements += 1
        return np.concatenate([se3.matrix_to_pose(M, "rotvec"), [time.monotonic() - self._t0]])
