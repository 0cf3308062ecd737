"""What every reader of a model file shares (serial in ``modelfile``, parallel in ``parallelfile``, the schema in
``modelschema``): the format name, the units a model file may state, the error and the one number rule. Its own
module so that each reader imports it without importing another reader (docs/architecture.md, "Import rules")."""

from __future__ import annotations

import numpy as np

FORMAT = "station-model/1"
LENGTH = {"m": 1.0, "mm": 1e-3}
ANGLE = {"rad": 1.0, "deg": np.pi / 180}
ANGLE_KEYS = {"alpha", "theta", "beta", "rx", "ry", "rz"}


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
