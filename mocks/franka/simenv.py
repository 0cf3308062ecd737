"""Where the franka-sim environment is and how its simulator process is started.

franka-sim pins numpy 1.26 and MuJoCo < 3.3, so it lives in a virtual environment of its own, made by the
project's files (``make franka-sim``: ``.venv-franka-sim`` next to ``.venv``) and never at run time. The
station finds its interpreter through, in order: ``STATION_FRANKA_SIM_PYTHON``, then
``.venv-franka-sim/bin/python`` in the source tree the station runs from."""

from __future__ import annotations

import os
import random
import socket
from pathlib import Path

from station.mocks.errors import MockError

ENV = "STATION_FRANKA_SIM_PYTHON"
FCI_PORT = 1337  # libfranka connects here; the port is fixed, so one simulated robot per address
SIMHOST = Path(__file__).with_name("simhost.py")


def sim_python(given: str | os.PathLike | None = None) -> Path:
    """The franka-sim environment's interpreter, or a one-line ``MockError`` saying how to make it."""
    if given:
        cand, how = Path(given), "--sim-python"
    elif os.environ.get(ENV):
        cand, how = Path(os.environ[ENV]), f"${ENV}"
    else:
        cand, how = Path(__file__).resolve().parents[2] / ".venv-franka-sim" / "bin" / "python", "the source tree"
    if not (cand.is_file() and os.access(cand, os.X_OK)):
        raise MockError(f"the franka-sim environment is missing ({how}: {cand} is not an interpreter); make it with "
                        f"`make franka-sim` in the station's source tree, or set {ENV}")
    return cand


def port_free(host: str, port: int = FCI_PORT) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_loopback() -> str:
    """A random loopback address 127.A.B.C whose FCI port is free (side-by-side emulators never collide)."""
    rng = random.Random()
    for _ in range(200):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 255)}.{rng.randint(2, 254)}"
        if port_free(host):
            return host
    raise MockError("no free loopback address for a Franka emulator")
