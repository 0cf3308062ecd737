"""The configuration-space correction map (docs/map.md): sample plans, the map (``station-map/1``),
calibrated control and measuring kinematics, for serial and parallel robots. Pure (numpy/scipy), SI, no I/O.

The ``correction_map`` procedure calls, in order: ``plan`` -> (drive, measure GDK(x)) -> ``build_map`` ->
``CorrectionMap.command`` / ``CorrectionMap.measure`` to verify held-out configurations -> ``to_dict``."""

from station.solver.map.cmap import FORMAT, CorrectionMap, build_map, second_configurations, working_model
from station.solver.map.grid import MESHES, Grid, grid_levels
from station.solver.map.plan import Plan, plan
from station.solver.map.poses import FULL, PLANAR, POSITION, MapError, check_columns, output_columns, to_vectors

__all__ = [
    "FORMAT", "FULL", "MESHES", "PLANAR", "POSITION", "CorrectionMap", "Grid", "MapError", "Plan", "build_map",
    "check_columns", "grid_levels", "output_columns", "plan", "second_configurations", "to_vectors",
    "working_model",
]
