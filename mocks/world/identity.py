"""The serial number an emulator reports when its world file names none: derived from the world itself.

Two worlds are two robots. A fixed default (every emulated UR was ``20235500001``) filed the sessions of two
different arms under one serial, so the records merged them and ``records show --trend`` called the difference
DRIFT. The serial is a digest of what makes the robot that robot as its world file states it: the model, the hidden
errors, the joint mechanics and the cell; not the time mode, the bus settings or the faults, so the same arm served
faster or on another bus keeps its serial, and restarting an emulator on the same file gives the same one (a
resume finds its robot)."""

from __future__ import annotations

import hashlib


def world_digest(world) -> str:
    """A digest of the world file's robot, hidden errors (as the file states them: explicit values and random
    sigmas with the seed), joint mechanics and cell; a model file by its absolute path. Not the drawn values nor
    the catalogue's parameters, so a station update that redraws or retunes a model keeps an emulator's serial."""
    import json

    doc = world.to_dict("m", "rad")
    keep = {k: doc.get(k) for k in ("seed", "robot", "errors", "joints", "cell")}
    source = (getattr(world.nominal, "source", None) or {}).get("urdf") or {}
    keep["model_path"] = str(source.get("path") or getattr(world.nominal, "path", "") or "")
    keep["model"] = str(getattr(world.nominal, "name", ""))
    text = json.dumps(keep, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def default_serial(world, kind: str = "ur") -> str:
    """``ur``: eleven digits as a UR controller's serial (``2023`` + 7 digits of the digest); ``canopen``: the
    base of the drives' 0x1018 serial numbers (node id added per drive), as hex-like 32-bit integer text;
    ``dynamixel``: the ``serial=`` an integrator writes into the robot URL (X-series servos carry no serial
    number, so the driver would otherwise derive one from the ids, the same for every arm)."""
    d = int(world_digest(world)[:15], 16)
    if kind == "ur":
        return f"2023{d % 10**7:07d}"
    if kind == "canopen":
        return str(0x5A000000 | ((d % 0xFFFF) << 8))
    if kind == "dynamixel":
        return f"DXL-{d % 16**8:08X}"
    if kind == "dynamixel":
        return f"DXL-{d % 16**8:08X}"
    raise ValueError(f"default_serial: unknown kind {kind!r}")
