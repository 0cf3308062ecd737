"""The simulated world behind every emulator: a robot with hidden kinematic errors, joint motion with
velocity/acceleration limits, a calibration cell (needles, sockets), fault injection. See docs/world.md."""

from station.mocks.world.cell import CellPoint
from station.mocks.world.faults import KINDS as FAULT_KINDS
from station.mocks.world.faults import Faults
from station.mocks.world.world import Snapshot, World, default_doc
from station.mocks.world.worldfile import WorldFileError

__all__ = ["FAULT_KINDS", "CellPoint", "Faults", "Snapshot", "World", "WorldFileError", "default_doc"]
