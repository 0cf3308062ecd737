"""The simulated world behind every emulator: a robot with hidden kinematic errors, joint motion with
velocity/acceleration limits, a calibration cell (needles, sockets), fault injection. See docs/world.md.

Names are imported on first use (PEP 562): `station mock --help` and the CLI's start-up register the world's
commands without loading numpy and the kinematics."""

from __future__ import annotations

import importlib

_WHERE = {
    "CellPoint": ("station.mocks.world.cell", "CellPoint"),
    "FAULT_KINDS": ("station.mocks.world.faults", "KINDS"),
    "Faults": ("station.mocks.world.faults", "Faults"),
    "Snapshot": ("station.mocks.world.world", "Snapshot"),
    "World": ("station.mocks.world.world", "World"),
    "default_doc": ("station.mocks.world.world", "default_doc"),
    "WorldFileError": ("station.mocks.world.worldfile", "WorldFileError"),
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    try:
        module, attr = _WHERE[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value
    return value
