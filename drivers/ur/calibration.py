"""UR kinematic calibration files: read an existing ``calibration.conf`` and export identified corrections.

A UR controller keeps its factory kinematic calibration internally (``calibration.conf``, section
``[mounting]``: per joint ``delta_theta`` (rad), ``delta_a`` (m), ``delta_d`` (m), ``delta_alpha`` (rad),
added to the published DH table). The station cannot write it into the controller over RTDE, so it exports:

* ``calibration.conf`` - same section and keys, SI units, for review and tools that read that file;
* ``ur_kinematics.yaml`` - per-joint origins (x, y, z, roll, pitch, yaw; m, rad) of the calibrated chain in the
  layout of ur_description's kinematics YAML, plus the calibrated DH table;
* ``ur_calibrated.urdf`` - the calibrated chain as a URDF (revolute joints about z, origins as above).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from station.kinematics import Model
from station.kinematics.se3 import matrix_to_rpy, rot_x, rot_y, rot_z, rpy_to_matrix
from station.robot.errors import ConfigError

KEYS = ("delta_theta", "delta_a", "delta_d", "delta_alpha")
UR_LINK_NAMES = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
_PARAM = {"delta_theta": "offset.j{}", "delta_a": "dh.j{}.a", "delta_d": "dh.j{}.d", "delta_alpha": "dh.j{}.alpha"}


def read_calibration_conf(path: str | Path, n: int = 6) -> dict[str, list[float]]:
    """``[mounting]`` deltas of a UR ``calibration.conf`` (SI). Missing keys are zeros."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"calibration file {p}: cannot read ({e.strerror or e})") from None
    section = None
    out = {k: [0.0] * n for k in KEYS}
    found = False
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        m = re.fullmatch(r"\[(\w+)\]", line)
        if m:
            section = m.group(1)
            continue
        if section != "mounting" or "=" not in line:
            continue
        key, value = (s.strip() for s in line.split("=", 1))
        if key not in KEYS:
            continue
        try:
            vals = [float(x) for x in value.strip("[] ").replace(",", " ").split()]
        except ValueError:
            raise ConfigError(f"calibration file {p} line {lineno}: {key} is not a list of numbers") from None
        if len(vals) != n or not all(math.isfinite(v) for v in vals):
            raise ConfigError(f"calibration file {p} line {lineno}: {key} needs {n} finite values, got {value!r}")
        out[key] = vals
        found = True
    if not found:
        raise ConfigError(f"calibration file {p}: no [mounting] delta_theta/delta_a/delta_d/delta_alpha found")
    return out


def deltas_to_params(deltas: dict[str, list[float]]) -> dict[str, float]:
    """``{"offset.j1": dtheta1, "dh.j1.a": da1, ...}`` (deltas, SI)."""
    out = {}
    for key, fmt in _PARAM.items():
        for i, v in enumerate(deltas.get(key, [])):
            out[fmt.format(i + 1)] = float(v)
    return out


def apply_deltas(model: Model, deltas: dict[str, list[float]]) -> Model:
    """The published model plus the controller's own calibration deltas: what the controller believes."""
    d = deltas_to_params(deltas)
    return model.with_params({k: model.param(k) + v for k, v in d.items() if k in model.param_names})


def deltas_from_values(catalog: Model, values: dict[str, float],
                       base: dict[str, list[float]] | None = None) -> tuple[dict[str, list[float]], list[str]]:
    """Absolute parameter values of the station's model -> deltas to the published table. Parameters not
    given keep ``base`` (the existing calibration.conf) or zero. Returns (deltas, names UR cannot store)."""
    n = catalog.n_joints
    out = {k: list((base or {}).get(k, [0.0] * n)) for k in KEYS}
    dropped: list[str] = []
    for name, value in values.items():
        if not math.isfinite(float(value)):
            raise ConfigError(f"calibration export: {name} = {value!r} is not finite")
        m = re.fullmatch(r"(offset|dh)\.j(\d+)(?:\.(\w+))?", name)
        key = None
        if m:
            kind, j, what = m.group(1), int(m.group(2)), m.group(3)
            key = "delta_theta" if kind == "offset" else {"a": "delta_a", "d": "delta_d",
                                                          "alpha": "delta_alpha"}.get(what)
        if key is None or not 1 <= j <= n:
            dropped.append(name)
            continue
        out[key][j - 1] = float(value) - catalog.param(name)
    return out, dropped


def _values_of(result_or_values) -> dict[str, float]:
    if isinstance(result_or_values, dict):
        return {str(k): float(v) for k, v in result_or_values.items()}
    values = getattr(result_or_values, "values", None)
    if callable(values):
        return {k: float(v) for k, v in values("model").items()}
    raise ConfigError("calibration export: expected a CalibrationResult or a {parameter: value} dict")


def _link_transform(a: float, d: float, alpha: float, theta: float, beta: float = 0.0) -> np.ndarray:
    """Fixed part of a standard DH link after the joint rotation: Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)."""
    rz = rot_z(theta)
    T = np.eye(4)
    T[:3, :3] = rz @ rot_x(alpha) @ rot_y(beta)
    T[:3, 3] = np.array([0.0, 0.0, d]) + rz @ np.array([a, 0.0, 0.0])
    return T


def _dh_table(model: Model) -> list[dict[str, float]]:
    links = model.source.get("links") if isinstance(model.source, dict) else None
    rows = []
    for i in range(model.n_joints):
        j = f"j{i + 1}"
        const = float(links[i].get("theta", 0.0)) if links else 0.0
        rows.append({"a": model.param(f"dh.{j}.a"), "d": model.param(f"dh.{j}.d"),
                     "alpha": model.param(f"dh.{j}.alpha"), "theta": const + model.param(f"offset.{j}"),
                     "beta": model.param(f"dh.{j}.beta") if f"dh.{j}.beta" in model.param_names else 0.0})
    return rows


def _origins(model: Model) -> list[np.ndarray]:
    """URDF joint origins: joint 1 at the base, joint k+1 at the fixed part of DH link k; last = flange."""
    out = [np.eye(4)]
    for row in _dh_table(model):
        out.append(_link_transform(row["a"], row["d"], row["alpha"], row["theta"], row["beta"]))
    return out


def _xyzrpy(T: np.ndarray) -> dict[str, float]:
    roll, pitch, yaw = matrix_to_rpy(T[:3, :3])  # URDF rpy: fixed axes X, Y, Z
    return {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3]),
            "roll": float(roll), "pitch": float(pitch), "yaw": float(yaw)}


def export_files(catalog: Model, deltas: dict[str, list[float]], folder: str | Path, *, serial: str,
                 note: str = "", dropped: list[str] | None = None) -> list[Path]:
    """Write calibration.conf, ur_kinematics.yaml and ur_calibrated.urdf into ``folder``."""
    import datetime

    import yaml

    if catalog.convention != "dh":
        raise ConfigError(f"UR calibration export needs a standard-DH model, {catalog.name} is {catalog.convention}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    when = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    head = (f"# station export for UR serial {serial}, model {catalog.name}, {when}\n"
            "# Units: delta_theta and delta_alpha in rad, delta_a and delta_d in m (added to the published DH table).\n"
            "# The controller keeps its own calibration; this export does NOT change the robot.\n")
    if note:
        head += f"# {note}\n"
    if dropped:
        head += f"# not representable in calibration.conf (kept only in the URDF/YAML): {', '.join(dropped)}\n"
    conf = head + "[mounting]\n" + "".join(
        f"{k} = [ {', '.join(f'{v:.12g}' for v in deltas[k])} ]\n" for k in KEYS)
    paths = [folder / "calibration.conf", folder / "ur_kinematics.yaml", folder / "ur_calibrated.urdf"]
    paths[0].write_text(conf)
    calibrated = apply_deltas(catalog, deltas)
    origins = _origins(calibrated)
    names = UR_LINK_NAMES if calibrated.n_joints == 6 else tuple(f"link_{i + 1}" for i in range(calibrated.n_joints))
    doc = {"format": "station-ur-kinematics/1", "serial": serial, "model": catalog.name,
           "units": {"length": "m", "angle": "rad"},
           "note": "per-joint origins of the calibrated chain (parent joint frame -> joint frame, URDF rpy)",
           "kinematics": {name: _xyzrpy(T) for name, T in zip(names, origins[:-1], strict=True)},
           "flange": _xyzrpy(origins[-1]),
           "dh": [{k: float(v) for k, v in row.items()} for row in _dh_table(calibrated)],
           "deltas": {k: [float(x) for x in v] for k, v in deltas.items()}}
    paths[1].write_text(head + yaml.safe_dump(doc, sort_keys=False))
    comment = "<!-- " + head.replace("# ", "").replace("\n", " ").replace("--", "-") + "-->"
    lines = ['<?xml version="1.0"?>', comment,
             f'<robot name="{catalog.name}_{serial}_calibrated">', '  <link name="base_link"/>']
    parent = "base_link"
    for i, (name, T) in enumerate(zip(names, origins[:-1], strict=True)):
        o = _xyzrpy(T)
        lo, hi = calibrated.joints[i].lower, calibrated.joints[i].upper
        vel = calibrated.joints[i].max_velocity
        lines += [f'  <link name="{name}_link"/>',
                  f'  <joint name="{name}_joint" type="revolute">',
                  f'    <parent link="{parent}"/>', f'    <child link="{name}_link"/>',
                  f'    <origin xyz="{o["x"]:.9g} {o["y"]:.9g} {o["z"]:.9g}" '
                  f'rpy="{o["roll"]:.9g} {o["pitch"]:.9g} {o["yaw"]:.9g}"/>',
                  '    <axis xyz="0 0 1"/>',
                  f'    <limit lower="{lo:.9g}" upper="{hi:.9g}" effort="150" velocity="{vel:.9g}"/>',
                  "  </joint>"]
        parent = f"{name}_link"
    o = _xyzrpy(origins[-1])
    lines += ['  <link name="flange"/>', '  <joint name="flange_joint" type="fixed">',
              f'    <parent link="{parent}"/>', '    <child link="flange"/>',
              f'    <origin xyz="{o["x"]:.9g} {o["y"]:.9g} {o["z"]:.9g}" '
              f'rpy="{o["roll"]:.9g} {o["pitch"]:.9g} {o["yaw"]:.9g}"/>', "  </joint>", "</robot>", ""]
    paths[2].write_text("\n".join(lines))
    return paths


def urdf_chain_fk(urdf_path: str | Path, q) -> np.ndarray:
    """Flange pose of an exported URDF at joint values ``q`` (for checking the export against the model)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(urdf_path).getroot()
    T = np.eye(4)
    q = list(np.asarray(q, dtype=float))
    for joint in root.findall("joint"):
        o = joint.find("origin")
        xyz = [float(v) for v in o.get("xyz").split()]
        rpy = [float(v) for v in o.get("rpy").split()]
        F = np.eye(4)
        F[:3, :3] = rpy_to_matrix(rpy)
        F[:3, 3] = xyz
        T = T @ F
        if joint.get("type") == "revolute":
            R = np.eye(4)
            R[:3, :3] = rot_z(q.pop(0))
            T = T @ R
    return T
