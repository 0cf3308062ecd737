"""A station world as franka-sim's scene: the files ``simhost.py`` (in the franka-sim environment) builds its
MuJoCo model from. SI units throughout (m, rad, N).

- ``true.urdf``: the world's TRUE arm (``world.truth``: nominal geometry plus the hidden errors, zero offsets
  folded into the joint origins, the ball centre as the tool link ``tool0``), written by
  ``station.kinematics.urdfexport`` with the model's link masses; no meshes;
- ``scene.json``: the sockets (true centres, approach directions) and the nest each becomes, the ball radius,
  the joint compliance, the seating noise, the external-force noise, the start pose, the address to serve on.

The robot serves franka-sim's bundled FR3 description over GetRobotModel (the nominal arm the station's
``fr3`` model is: checked here), so the world's model must be ``fr3``.

The world file's ``buses.franka`` section (all optional): ``host`` (loopback address), ``ball_radius`` (m,
default 0.006), ``nest`` ({spheres: 8, sphere_radius: 0.002, half_angle_deg: 45}), ``friction`` (0.15),
``force_noise`` (N per axis of the external-force estimate, default 0.2), ``enforce_comm`` and
``enforce_limits`` (franka-sim's reflexes on communication and motion-limit violations, default on)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from station.mocks.errors import MockError

from station.kinematics import load_model

BALL_RADIUS = 0.006  # m: a 12 mm steel ball on the flange
NEST = {"spheres": 8, "sphere_radius": 0.002, "half_angle_deg": 45.0}  # a cone of 8 hard points, 90 deg
FORCE_NOISE = 0.2  # N per axis: the filtered external-force estimate at rest (assumed; docs/hardware-franka.md)
MODEL = "fr3"
SETTINGS = {"host", "ball_radius", "nest", "friction", "force_noise", "enforce_comm", "enforce_limits", "serial"}


def check_world(world) -> None:
    """The world must be an FR3 with a ball tool in front of sockets (what this emulator can build)."""
    if world.nominal.name != MODEL or world.nominal.n_joints != 7:
        raise MockError(f"world: robot.model must be {MODEL} for the Franka emulator (it serves the FR3 "
                        f"description over GetRobotModel), got {world.nominal.name}")
    ref = load_model(MODEL)
    for name in ref.param_names:  # the world's nominal arm is the served one (a tool is the world's own)
        if name.startswith(("tcp.", "compliance.")):
            continue
        if abs(world.nominal.param(name) - ref.param(name)) > 1e-12:
            raise MockError(f"world: the nominal {name} differs from the FR3 description the robot serves")
    unknown = sorted(set(world.bus_config("franka")) - SETTINGS)
    if unknown:
        raise MockError(f"world: buses.franka: unknown keys {unknown} (known: {sorted(SETTINGS)})")
    if not any(p.kind == "socket" for p in world.points.values()):
        raise MockError("world: cell.points has no socket: the Franka emulator seats a ball in sockets")


def _number(cfg: dict, key: str, default: float, positive: bool = True) -> float:
    v = cfg.get(key, default)
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise MockError(f"world: buses.franka.{key}: {v!r} is not a number") from None
    if not np.isfinite(x) or (positive and x <= 0) or x < 0:
        raise MockError(f"world: buses.franka.{key}: must be a {'positive' if positive else 'non-negative'} "
                        f"number, got {v!r}")
    return x


def write_scene(world, folder: str | Path, host: str) -> Path:
    """Write ``true.urdf`` and ``scene.json`` for ``world`` into ``folder``; returns the scene file."""
    from station.kinematics.urdfexport import urdf_text

    check_world(world)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cfg = world.bus_config("franka")
    truth = world.truth
    (folder / "true.urdf").write_text(urdf_text(truth, note="TRUE arm of a station world (hidden errors)"),
                                      encoding="utf-8")
    nest = dict(NEST)
    given = cfg.get("nest") or {}
    if not isinstance(given, dict) or set(given) - set(NEST):
        raise MockError(f"world: buses.franka.nest: expected a mapping with keys {sorted(NEST)}, got {given!r}")
    for k in NEST:
        nest[k] = _number(given, k, NEST[k])
    compliance = [float(c) for c in world.gravity.compliance] if world.gravity.active else [0.0] * 7
    scene = {
        "format": "station-franka-scene/1",
        "host": host,
        "true_urdf": str(folder / "true.urdf"),
        "served_urdf": None,  # franka-sim's bundled fr3.urdf
        "tool_link": "tool0",
        "ball_radius": _number(cfg, "ball_radius", BALL_RADIUS),
        "nest": nest,
        "friction": _number(cfg, "friction", 0.15, positive=False),
        "sockets": [{"label": p.label, "position": p.position.tolist(), "approach": p.approach.tolist()}
                    for p in world.points.values() if p.kind == "socket"],
        "seating_sigma": float(world.spec.seating_sigma),
        "compliance": compliance,
        "force_noise": _number(cfg, "force_noise", FORCE_NOISE, positive=False),
        "start_q": [float(x) for x in world.encoder_q()],
        "seed": int(world.spec.seed),
        "enforce_comm": bool(cfg.get("enforce_comm", True)),
        "enforce_limits": bool(cfg.get("enforce_limits", True)),
    }
    path = folder / "scene.json"
    path.write_text(json.dumps(scene, indent=1), encoding="utf-8")
    return path
