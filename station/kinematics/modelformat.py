"""What every reader of a model file shares (serial in ``modelfile``, parallel in ``parallelfile``, the schema in
``modelschema``): the format name, the units a model file may state, the error and the one number rule. Its own
module so that each reader imports it without importing another reader (docs/architecture.md, "Import rules")."""

from __future__ import annotations

import numpy as np

from station.units import ANGLE_PARAMS, ANGLE_UNITS, LENGTH_UNITS

FORMAT = "station-model/1"
LENGTH = {u: LENGTH_UNITS[u] for u in ("m", "mm")}  # the units a model file may state
ANGLE = {u: ANGLE_UNITS[u] for u in ("rad", "deg")}
ANGLE_KEYS = ANGLE_PARAMS  # the keys of a frame or a link table that are angles (station.units' one rule)


class ModelFileError(ValueError):
    """Malformed model file; the message names the file and the field."""


def number(v, where: str) -> float:
    """A model file's number: finite, and written as a number (``true`` is not 1, ``"1_0"`` is not 10)."""
    try:
        x = float(v)
    except (TypeError, ValueError, OverflowError):
        raise ModelFileError(f"{where}: expected a number, got {v!r}") from None
    if isinstance(v, bool | str):
        raise ModelFileError(f"{where}: expected a number, got {v!r}")
    if not np.isfinite(x):
        raise ModelFileError(f"{where}: not a finite number ({v!r})")
    return x
