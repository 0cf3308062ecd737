"""The serial number an emulator reports when its world file names none: derived from the world itself.

Two worlds are two robots. A fixed default (every emulated UR was ``20235500001``) filed the sessions of two
different arms under one serial, so the records merged them and ``records show --trend`` called the difference
DRIFT. The serial is a digest of what makes the robot that robot: the nominal model's parameters and joints, the
true (hidden) parameters and the cell; not the time mode, the bus settings or the faults, so the same arm served
faster or on another bus keeps its serial, and restarting an emulator on the same file gives the same one (a
resume finds its robot)."""

from __future__ import annotations

import hashlib

import numpy as np


def world_digest(world) -> str:
    h = hashlib.sha256()
    for model in (world.nominal, world.truth):
        h.update(str(getattr(model, "name", "")).encode())
        h.update(np.round(np.asarray(model.params, float), 12).tobytes())
        h.update(np.round(np.concatenate([model.lower, model.upper]), 12).tobytes())
    for label, p in sorted(world.points.items()):
        h.update(label.encode() + p.kind.encode() + np.round(p.position, 9).tobytes())
    return h.hexdigest()


def default_serial(world, kind: str = "ur") -> str:
    """``ur``: eleven digits as a UR controller's serial (``2023`` + 7 digits of the digest); ``canopen``: the
    base of the drives' 0x1018 serial numbers (node id added per drive), as hex-like 32-bit integer text."""
    d = int(world_digest(world)[:15], 16)
    if kind == "ur":
        return f"2023{d % 10**7:07d}"
    if kind == "canopen":
        return str(0x5A000000 | ((d % 0xFFFF) << 8))
    raise ValueError(f"default_serial: unknown kind {kind!r}")
