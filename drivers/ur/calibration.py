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
from dataclasses import replace
from pathlib import Path

import numpy as np

from station.kinematics import Model
from station.kinematics.dhtable import DHTable, dh_table, link
from station.kinematics.se3 import invert, matrix_to_rpy, rot_x, rot_y, rot_z, rpy_to_matrix
from station.robot.errors import ConfigError

KEYS = ("delta_theta", "delta_a", "delta_d", "delta_alpha")
UR_LINK_NAMES = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")


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


# ---- the one conversion: a controller's DH rows <-> the station's model ----------------------------------
def flange_of(model: Model) -> Model:
    """``model`` without its tool (what a controller's DH rows describe ends at the flange)."""
    return model.with_params({f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")})


def published_table(catalog: Model) -> DHTable:
    """The published plain-DH table of the arm a model describes (its own nominal geometry)."""
    return dh_table(flange_of(catalog))


def table_from_deltas(catalog: Model, deltas: dict[str, list[float]]) -> DHTable:
    """A ``calibration.conf``'s ``[mounting]`` deltas added to the published table: the rows the controller
    then reports (KinematicsInfo), ``base``/``flange`` of the published table."""
    pub = published_table(catalog)
    return replace(pub, theta=pub.theta + np.asarray(deltas["delta_theta"], float),
                   a=pub.a + np.asarray(deltas["delta_a"], float), d=pub.d + np.asarray(deltas["delta_d"], float),
                   alpha=pub.alpha + np.asarray(deltas["delta_alpha"], float))


def table_from_rows(catalog: Model, theta, a, d, alpha) -> DHTable:
    """Rows as a controller reports them (KinematicsInfo), placed in the model's frames by its published
    table's ``base``/``flange`` (identity for the built-in UR models)."""
    pub = published_table(catalog)
    return replace(pub, theta=np.asarray(theta, float), a=np.asarray(a, float), d=np.asarray(d, float),
                   alpha=np.asarray(alpha, float))


def deltas_of(catalog: Model, table: DHTable) -> dict[str, list[float]]:
    """``[mounting]`` deltas of ``table`` to the published table (theta wrapped to (-pi, pi])."""
    pub = published_table(catalog)
    dth = (table.theta - pub.theta + np.pi) % (2 * np.pi) - np.pi
    return {"delta_theta": dth.tolist(), "delta_a": (table.a - pub.a).tolist(),
            "delta_d": (table.d - pub.d).tolist(), "delta_alpha": (table.alpha - pub.alpha).tolist()}


def table_fk(catalog: Model, table: DHTable, q) -> np.ndarray:
    """Tool pose of the controller's raw rows with the model's tool: what the converted model must equal."""
    tool = catalog.fk(np.zeros(catalog.n_joints))
    tool = invert(flange_of(catalog).fk(np.zeros(catalog.n_joints))) @ tool
    return table.fk(q) @ tool


class ConversionError(ConfigError):
    pass


def _wrap(angle: float, near: float = 0.0) -> float:
    return near + (angle - near + math.pi) % (2 * math.pi) - math.pi


def _dh_params(catalog: Model, table: DHTable) -> dict[str, float]:
    """The re-intersected DH(+Hayati beta) parameters of a standard-DH model whose joints follow ``table``'s rows
    exactly: where the model's link is a Hayati one (``dh.jN.beta`` in its ``dh`` group: nearly parallel axes)
    the next axis is intersected with the plane of the model's own ``d`` (as UR's ur_calibration does: the d of
    hundreds of metres goes, a beta comes), and the next row takes what the frame moved along and about its
    axis; every other link is the controller's row."""
    n = catalog.n_joints
    links = catalog.source.get("links") if isinstance(catalog.source, dict) else None
    hayati = {i for i in range(n - 1) if f"dh.j{i + 1}.beta" in catalog.groups.get("dh", ())}
    phi = t = 0.0  # the controller's frame i-1 = ours @ Rz(phi) Tz(t): both lie on joint i's axis
    out: dict[str, float] = {}
    for i in range(n):
        j = f"j{i + 1}"
        const = float(links[i].get("theta", 0.0)) if links else 0.0
        th_c, d_c, a_c, al_c = (float(v[i]) for v in (table.theta, table.d, table.a, table.alpha))
        if i in hayati:
            X = link(phi + th_c, t + d_c, a_c, al_c)[0]  # the controller's frame i in ours i-1
            p, w = X[:3, 3], X[:3, 2]
            d = catalog.param(f"dh.{j}.d")
            P = p + ((d - p[2]) / w[2]) * w  # the next axis meets the plane z = d here
            r = math.hypot(P[0], P[1])
            if catalog.param(f"dh.{j}.a") < 0:
                theta, a = math.atan2(-P[1], -P[0]), -r
            else:
                theta, a = math.atan2(P[1], P[0]), r
            wl = rot_z(-theta) @ w
            beta = math.asin(max(-1.0, min(1.0, float(wl[0]))))
            alpha = math.atan2(-float(wl[1]), float(wl[2]))
            ours = link(theta, d, a, alpha)[0]
            ours[:3, :3] = ours[:3, :3] @ rot_y(beta)
            M = invert(ours) @ X
            phi, t = math.atan2(M[1, 0], M[0, 0]), float(M[2, 3])
        else:
            theta, d, a, alpha, beta = phi + th_c, t + d_c, a_c, al_c, 0.0
            phi = t = 0.0
        out[f"offset.{j}"] = _wrap(theta - const, catalog.param(f"offset.{j}"))
        out[f"dh.{j}.d"], out[f"dh.{j}.a"], out[f"dh.{j}.alpha"], out[f"dh.{j}.beta"] = d, a, alpha, beta
    return out


def _fit_params(catalog: Model, table: DHTable, qs: np.ndarray) -> dict[str, float]:
    """Any other convention (MDH, POE, a URDF): the model's arm parameters (all but base, tool, compliance) fitted
    to the rows' flange poses by Gauss-Newton with the model's analytic Jacobian (exact when the convention can
    hold the geometry, as MDH with Hayati beta and local POE can)."""
    from station.kinematics.se3 import orientation_error

    names = [nm for nm in catalog.param_names if nm.split(".", 1)[0] not in ("base", "tcp", "compliance")]
    idx = [catalog.index(nm) for nm in names]
    flange = flange_of(catalog)
    target = table.fk(qs)
    p = flange.params.copy()
    for _ in range(40):
        T, _, Jp = flange.jacobians(qs, p)
        r = np.concatenate([(T[:, :3, 3] - target[:, :3, 3]).reshape(-1),
                            -np.stack([orientation_error(target[k, :3, :3], T[k, :3, :3])
                                       for k in range(len(qs))]).reshape(-1)])
        if np.max(np.abs(r)) < 1e-13:
            break
        J = np.concatenate([Jp[:, :3, idx].reshape(-1, len(idx)), Jp[:, 3:, idx].reshape(-1, len(idx))])
        p[idx] += np.linalg.lstsq(J, -r, rcond=1e-12)[0]
    return {nm: float(p[k]) for nm, k in zip(names, idx, strict=True)}


def controller_model(catalog: Model, table: DHTable, *, source: str = "controller") -> Model:
    """The station's model of the arm the controller describes with ``table``: the model's convention and
    parameter names, its base and tool, the joints exactly where the rows put them (re-intersected, see
    ``_dh_params``). Checked: its tool pose equals the raw rows' at random joints to 1e-9 m / 1e-9 rad, else a
    one-line ``ConfigError`` naming ``source``."""
    rng = np.random.default_rng(0)
    lo, hi = np.maximum(catalog.lower, -np.pi), np.minimum(catalog.upper, np.pi)
    qs = rng.uniform(lo, hi, size=(24, catalog.n_joints))
    values = _dh_params(catalog, table) if catalog.convention == "dh" else _fit_params(catalog, table, qs)
    model = catalog.with_params(values)
    check = rng.uniform(lo, hi, size=(24, catalog.n_joints))
    want, got = table_fk(catalog, table, check), model.fk(check)
    pos = float(np.max(np.linalg.norm(want[:, :3, 3] - got[:, :3, 3], axis=1)))
    rot = float(np.max(np.abs(want[:, :3, :3] - got[:, :3, :3])))
    if not (pos < 1e-9 and rot < 1e-9):
        raise ConversionError(f"{source}: the controller's kinematics cannot be expressed in model {catalog.name} "
                              f"({catalog.convention}): tool off by {pos * 1e3:.3g} mm after conversion; use a "
                              "model of this arm whose chain has the controller's joint axes")
    return model


def calibrated_table(catalog: Model, model: Model) -> DHTable:
    """The controller's rows for a station model (its plain DH, signs as the published table): the inverse of
    ``controller_model``, what an export writes."""
    return dh_table(flange_of(model), hint=published_table(catalog))


def _values_of(result_or_values) -> dict[str, float]:
    if isinstance(result_or_values, dict):
        return {str(k): float(v) for k, v in result_or_values.items()}
    values = getattr(result_or_values, "values", None)
    if callable(values):
        return {k: float(v) for k, v in values("model").items()}
    raise ConfigError("calibration export: expected a CalibrationResult or a {parameter: value} dict")


def _origins(model: Model) -> tuple[list[np.ndarray], list[int]]:
    """URDF joint origins of ``model``'s flange chain (any convention): origin k = frame after joint k-1 -> frame
    after joint k, both at q = 0, so that the URDF's ``origin @ R(axis, q)`` chain equals the model; the last entry
    is the flange. Also each joint's rotation axis (0 x, 1 y, 2 z of its frame)."""
    from station.kinematics.chain import forward

    flange = flange_of(model)
    n = model.n_joints
    T, prefix = forward(flange.chain, np.zeros((1, n)), flange.params, keep_prefix=True)
    prev, origins, axes = np.eye(4), [], []
    for i in range(n):
        k = int(np.flatnonzero(flange.chain.joint == i)[0])
        after = prefix[0, k + 1] if k + 1 < flange.chain.n_elements else T[0]
        origins.append(invert(prev) @ after)
        axes.append(int(flange.chain.axis[k]) % 3)
        prev = after
    origins.append(invert(prev) @ T[0])
    return origins, axes


def _xyzrpy(T: np.ndarray) -> dict[str, float]:
    roll, pitch, yaw = matrix_to_rpy(T[:3, :3])  # URDF rpy: fixed axes X, Y, Z
    return {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3]),
            "roll": float(roll), "pitch": float(pitch), "yaw": float(yaw)}


def export_files(catalog: Model, calibrated: Model, folder: str | Path, *, serial: str,
                 note: str = "", dropped: list[str] | None = None) -> list[Path]:
    """Write calibration.conf (the ``[mounting]`` deltas a controller would hold for ``calibrated``: its plain-DH
    rows minus the published table, with the compensating metres on nearly parallel joints, at full precision),
    ur_kinematics.yaml and ur_calibrated.urdf (the re-intersected chain: joints where they physically are)."""
    import datetime

    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    table = calibrated_table(catalog, calibrated)
    deltas = deltas_of(catalog, table)
    when = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    head = (f"# station export for UR serial {serial}, model {catalog.name}, {when}\n"
            "# Units: delta_theta and delta_alpha in rad, delta_a and delta_d in m (added to the published DH table).\n"
            "# The controller keeps its own calibration; this export does NOT change the robot.\n")
    if note:
        head += f"# {note}\n"
    if dropped:
        head += f"# not representable in calibration.conf (kept only in the URDF/YAML): {', '.join(dropped)}\n"
    conf = head + "[mounting]\n" + "".join(
        f"{k} = [ {', '.join(repr(float(v)) for v in deltas[k])} ]\n" for k in KEYS)
    paths = [folder / "calibration.conf", folder / "ur_kinematics.yaml", folder / "ur_calibrated.urdf"]
    paths[0].write_text(conf)
    origins, axes = _origins(calibrated)
    n = calibrated.n_joints
    names = UR_LINK_NAMES if n == 6 else tuple(f"link_{i + 1}" for i in range(n))
    doc = {"format": "station-ur-kinematics/1", "serial": serial, "model": catalog.name,
           "units": {"length": "m", "angle": "rad"},
           "note": "per-joint origins of the calibrated chain (parent joint frame -> joint frame, URDF rpy)",
           "kinematics": {name: _xyzrpy(T) for name, T in zip(names, origins[:-1], strict=True)},
           "flange": _xyzrpy(origins[-1]),
           "dh": [{"theta": float(r[0]), "d": float(r[1]), "a": float(r[2]), "alpha": float(r[3])}
                  for r in table.rows()],
           "deltas": deltas}
    paths[1].write_text(head + yaml.safe_dump(doc, sort_keys=False))
    comment = "<!-- " + head.replace("# ", "").replace("\n", " ").replace("--", "-") + "-->"
    lines = ['<?xml version="1.0"?>', comment,
             f'<robot name="{catalog.name}_{serial}_calibrated">', '  <link name="base_link"/>']
    parent = "base_link"
    for i, (name, T) in enumerate(zip(names, origins[:-1], strict=True)):
        o = _xyzrpy(T)
        lo, hi = calibrated.joints[i].lower, calibrated.joints[i].upper
        vel = calibrated.joints[i].max_velocity
        axis = " ".join("1" if k == axes[i] else "0" for k in range(3))
        lines += [f'  <link name="{name}_link"/>',
                  f'  <joint name="{name}_joint" type="revolute">',
                  f'    <parent link="{parent}"/>', f'    <child link="{name}_link"/>',
                  f'    <origin xyz="{o["x"]!r} {o["y"]!r} {o["z"]!r}" '
                  f'rpy="{o["roll"]!r} {o["pitch"]!r} {o["yaw"]!r}"/>',
                  f'    <axis xyz="{axis}"/>',
                  f'    <limit lower="{lo:.9g}" upper="{hi:.9g}" effort="150" velocity="{vel:.9g}"/>',
                  "  </joint>"]
        parent = f"{name}_link"
    o = _xyzrpy(origins[-1])
    lines += ['  <link name="flange"/>', '  <joint name="flange_joint" type="fixed">',
              f'    <parent link="{parent}"/>', '    <child link="flange"/>',
              f'    <origin xyz="{o["x"]!r} {o["y"]!r} {o["z"]!r}" '
              f'rpy="{o["roll"]!r} {o["pitch"]!r} {o["yaw"]!r}"/>', "  </joint>", "</robot>", ""]
    paths[2].write_text("\n".join(lines))
    return paths


def urdf_chain_fk(urdf_path: str | Path, q) -> np.ndarray:
    """Flange pose of an exported URDF at joint values ``q`` (for checking the export against the model)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(urdf_path).getroot()
    T = np.eye(4)
    q = list(np.asarray(q, dtype=float))
    turn = {(1.0, 0.0, 0.0): rot_x, (0.0, 1.0, 0.0): rot_y, (0.0, 0.0, 1.0): rot_z}
    for joint in root.findall("joint"):
        o = joint.find("origin")
        xyz = [float(v) for v in o.get("xyz").split()]
        rpy = [float(v) for v in o.get("rpy").split()]
        F = np.eye(4)
        F[:3, :3] = rpy_to_matrix(rpy)
        F[:3, 3] = xyz
        T = T @ F
        if joint.get("type") == "revolute":
            axis = tuple(float(v) for v in joint.find("axis").get("xyz").split())
            R = np.eye(4)
            R[:3, :3] = turn[axis](q.pop(0))
            T = T @ R
    return T
