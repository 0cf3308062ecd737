"""Where the emulated tracker stands and what it measures: ``buses.tracker`` of the world file (docs/map.md).

```yaml
buses:
  tracker:
    units: {length: mm, angle: deg}        # required when any length or angle below is given
    pose: {x: 2500, y: 0, z: 1000, rx: 0, ry: 0, rz: 90}   # instrument frame in the robot base frame (fixed-axis rpy)
    reflectors: [[100, 0, 20], [-50, 86.6, 20], [-50, -86.6, 20]]   # >= 3 reflectors on the tool (tool frame)
    serial: LT-0001
    model: LT-EMU                          # with the serial, the identity ID reports (a resume checks it)
    noise: true                            # false: exact readings (the instrument's noise off)
```

Every key is optional; the defaults are the instrument 2.7 m from the base (as in bench/map.py) and a
three-reflector 6-DoF probe."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from station.mocks.errors import MockError

from station.kinematics import se3

DEFAULT_POSE = (2.5, 0.0, 1.0, 0.0, 0.0, np.pi / 2)  # m, rad (x, y, z, rx, ry, rz fixed-axis rpy)
DEFAULT_REFLECTORS = ((0.10, 0.0, 0.02), (-0.05, 0.0866, 0.02), (-0.05, -0.0866, 0.02))  # m, tool frame
LENGTH = {"m": 1.0, "mm": 1e-3}
ANGLE = {"rad": 1.0, "deg": np.pi / 180}
KEYS = {"units", "pose", "reflectors", "serial", "model", "noise"}


@dataclass(frozen=True)
class TrackerConfig:
    tracker_in_base: np.ndarray  # 4x4, SI
    reflectors: np.ndarray  # (K, 3) m, tool frame
    serial: str = "LT-EMU-0001"
    noise: bool = True
    model: str = "LT-EMU"  # what ID reports as model= (with the serial: the instrument's identity)


def tracker_config(doc: dict | None, where: str = "buses.tracker") -> TrackerConfig:
    """The tracker of a world's ``buses.tracker`` mapping (``World.bus_config("tracker")``); MockError names
    the field."""
    doc = dict(doc or {})
    if not isinstance(doc, dict):
        raise MockError(f"{where}: expected a mapping")
    unknown = sorted(set(doc) - KEYS)
    if unknown:
        raise MockError(f"{where}.{unknown[0]}: unknown key (one of {', '.join(sorted(KEYS))})")
    units = doc.get("units")
    if units is None and ("pose" in doc or "reflectors" in doc):
        raise MockError(f"{where}.units: state the units of pose and reflectors ({{length: mm, angle: deg}})")
    units = units or {"length": "m", "angle": "rad"}
    if not isinstance(units, dict) or units.get("length") not in LENGTH or units.get("angle") not in ANGLE:
        raise MockError(f"{where}.units: expected {{length: m|mm, angle: rad|deg}}, got {units!r}")
    fl, fa = LENGTH[units["length"]], ANGLE[units["angle"]]
    pose = np.array(DEFAULT_POSE, float)
    if "pose" in doc:
        p = doc["pose"]
        if not isinstance(p, dict) or set(p) - {"x", "y", "z", "rx", "ry", "rz"}:
            raise MockError(f"{where}.pose: expected {{x, y, z, rx, ry, rz}}")
        try:
            pose = np.array([float(p.get(k, 0.0)) * (fl if k in "xyz" else fa)
                             for k in ("x", "y", "z", "rx", "ry", "rz")])
        except (TypeError, ValueError):
            raise MockError(f"{where}.pose: every value must be a number") from None
    refl = np.array(DEFAULT_REFLECTORS, float)
    if "reflectors" in doc:
        try:
            refl = np.array(doc["reflectors"], dtype=float) * fl
        except (TypeError, ValueError):
            raise MockError(f"{where}.reflectors: expected [[x, y, z], ...] numbers") from None
        if refl.ndim != 2 or refl.shape[1] != 3 or len(refl) < 3:
            raise MockError(f"{where}.reflectors: a 6-DoF probe needs at least 3 reflectors [x, y, z]")
        if np.linalg.matrix_rank(refl - refl.mean(axis=0), tol=1e-6) < 2:
            raise MockError(f"{where}.reflectors: the reflectors lie on one line; the probe's rotation is unknown")
    noise = doc.get("noise", True)
    if not isinstance(noise, bool):
        raise MockError(f"{where}.noise: expected true or false")
    model = str(doc.get("model", "LT-EMU"))
    if not model or any(c.isspace() or c == "=" for c in model):
        raise MockError(f"{where}.model: one word without spaces or '=', got {model!r}")
    return TrackerConfig(se3.pose_to_matrix(pose, "rpy"), refl, str(doc.get("serial", "LT-EMU-0001")), noise, model)
