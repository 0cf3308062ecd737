"""What the Franka tests share: a world for franka-sim (an FR3 with a ball 60 mm beyond the flange, hidden
geometric errors, a two-socket fixture 50 mm apart) and the station-side cell of it (with the fixture's
certified distance). SI units in the documents below (m, rad)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

SEATING = 10e-6  # m per axis: where the ball settles in a socket from one seating to the next
TOOL = {"x": 0.003, "y": -0.002, "z": 0.167, "rx": 0.0, "ry": 0.0, "rz": 0.0}  # ball centre on the flange
SOCKETS = {"A": [0.50, -0.025, 0.10], "B": [0.50, 0.025, 0.10]}


# link masses (kg) and centres (m, Craig link frames) of franka_description's fr3.urdf: the simulator's links
FR3_MASSES = {
    "j1": (2.9274653454, [0.0000004128, -0.0181251324, -0.0386035970]),
    "j2": (2.9355370338, [0.0031828864, -0.0743221644, 0.0088146084]),
    "j3": (2.2449013699, [0.0407015686, -0.0048200565, -0.0289730823]),
    "j4": (2.6155955791, [-0.0459100965, 0.0630492960, -0.0085187868]),
    "j5": (2.3271207594, [-0.0016039605, 0.0292536262, -0.0972965990]),
    "j6": (1.8170376524, [0.0597131221, -0.0410294666, -0.0101692726]),
    "j7": (0.6271432862, [0.0045225817, 0.0086261921, -0.0161633251]),
}


def world_doc(seed: int = 3, errors: dict | None = None, compliance: dict | None = None, **buses) -> dict:
    joints = {}
    if compliance:  # rad per N m; the world's gravity model then needs the links' masses
        joints = {"compliance": dict(compliance),
                  "masses": {j: {"mass": m, "com": list(c)} for j, (m, c) in FR3_MASSES.items()}}
    return {
        "format": "station-world/1", "description": "FR3 with a ball, two sockets 50 mm apart",
        "units": {"length": "m", "angle": "rad", "time": "s", "mass": "kg"}, "seed": seed,
        "robot": {"model": "fr3", "tool": dict(TOOL)},
        "errors": errors if errors is not None else {"random": {
            "offsets": {"angle": math.radians(0.02)}, "dh": {"length": 0.2e-3, "angle": math.radians(0.02)},
            "tcp": {"length": 0.5e-3}}},
        "cell": {"points": [{"label": k, "kind": "socket", "position": p, "approach": [0, 0, 1]}
                            for k, p in SOCKETS.items()]},
        "noise": {"seating": SEATING},
        "buses": {"franka": dict(buses)} if buses else {},
        **({"joints": joints} if joints else {}),
    }


def write_world(folder: Path, name: str = "world.yaml", **kw) -> Path:
    path = Path(folder) / name
    path.write_text(yaml.safe_dump(world_doc(**kw)))
    return path


def write_cell(world, path: Path) -> Path:
    """The integrator's cell file: the world's approximate socket positions and the ball, plus the fixture's
    certified distance (the true one, stated to 1 um)."""
    doc = world.station_cell()
    a, b = (world.points[k].position for k in ("A", "B"))
    doc["distances"] = [{"between": ["A", "B"], "distance": float(np.linalg.norm(a - b)), "std": 1e-6}]
    path.write_text(yaml.safe_dump(doc))
    return path


def ik_down(model, point, seed_q, height: float = 0.0) -> np.ndarray:
    """Joints that put ``model``'s tool ``height`` m above ``point``, pointing down, near ``seed_q``."""
    T = model.fk(np.asarray(seed_q, float))
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = np.asarray(point, float) + [0.0, 0.0, height]
    W = np.ones(model.n_joints)
    W[2] = 0.0
    r = model.ik(T, seed_q, weights=W)
    assert r.ok[0], "no IK solution"
    return r.q[0]
