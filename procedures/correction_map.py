"""Correction map (docs/map.md): measure the tool pose at every configuration of the sample grid with a laser
tracker, build the configuration-space correction map, verify it on held-out configurations.

Technician: mount the 6-DoF probe on the tool, set the tracker up with a free line of sight to the whole
workspace and give its address (``--tracker tcp://HOST:PORT``). The robot is driven through the grid of
actuator levels (``--grid Q``, default 2: Q + 1 levels per actuator) and a few random held-out configurations;
each is read and measured at rest and journaled before the next move, so a resumed session measures only what
is missing. The tracker's frame is registered to the base frame by a best fit on the grid samples; the
held-out configurations are never used to build or register. Limits: ``procedures/limits.yaml``, section
``correction_map``. The map (``station-map/1``) is written to the session folder as ``map.json`` and stored in
the record (``correction_map``).

On top of a parametric calibration (``--calibration result.json``, a ``station solve`` result of this robot's
model): the file is checked before anything moves and journaled (a resume uses the same one and refuses a
changed file); the summands are what the calibrated model leaves (compliance, backlash, gear errors), and the
held-out configurations compare the calibrated model alone with the calibrated model plus the map. A calibration
with compliance terms (``station solve --payload 15kg --identify ...,compliance``) needs the same payload here
(``--payload 15kg``): the model then carries it and the calibration is applied with the joints' deflection."""

import json
from pathlib import Path

import numpy as np
from station.procedures._calibration import (
    CALIBRATION,
    PAYLOAD,
    TRACKER,
    calibration,
    journaled_calibration,
    payload,
    working,
)

from station.engine import events as ev
from station.engine.declare import HOLDOUT, SEED, Measurement, Option, angle, choice, count, measures, takes
from station.engine.plan import PlannedPose, PosePlan
from station.engine.steps import step
from station.kinematics import se3
from station.robot.errors import ConfigError, DeviceFault
from station.solver.map import FULL, POSITION, MapError, build_map, plan, to_vectors
from station.solver.map.plan import predicted_residual
from station.solver.map.register import register

DEFAULTS = {"grid": 2, "mesh": "simplex", "n_holdout": 12}
HOLDOUT_INSET = 0.1  # held-out configurations are drawn this fraction of each actuator range inside the grid box
APPROACH = np.radians(0.5)  # serial arms: every configuration is approached from this far below (> backlash)
APPROACH_LENGTH = 0.5e-3  # m, the same for a prismatic joint
PREDICTED_LIMIT = 0.5  # serial arms: refuse a work box where the map would leave more than this of a pose error

GRID = Option("grid", "--grid", count(1, 100, "sub-intervals 1..100"), "Q sub-intervals per actuator (Q+1 levels).",
              "count")
MESH = Option("mesh", "", choice("grid", "simplex"), "How the map interpolates between its nodes: grid "
              "(multilinear) or simplex (barycentric).")
SPAN = Option("span_deg", "--span-deg", angle(0, 90, "deg", "20deg", "a half-width"), "With a serial arm: the work "
              "box is +- this angle per joint around the start pose: 20deg (a bare number is degrees).", "deg", "20")


@measures(
    Measurement("registration_rms", "mm", "RMS residual of the tracker frame's registration (grid samples)"),
    Measurement("samples", "count", "grid samples the map is built from"),
    Measurement("predicted_residual", "1", "serial arms: the plan's singularity check"),
    Measurement("summand_max_length", "mm", "largest correction of a prismatic actuator"),
    Measurement("summand_max_angle", "deg", "largest correction of a revolute actuator"),
    Measurement("holdout", "count", "held-out configurations measured"),
    Measurement("holdout_nominal_rms", "mm", "held out: RMS position error of the nominal model"),
    Measurement("calibration_parameters", "count", "parameters of the --calibration the map sits on"),
    Measurement("holdout_calibrated_rms", "mm", "held out: RMS position error of the calibrated model alone"),
    Measurement("holdout_calibrated_max", "mm", "held out: largest position error of the calibrated model alone"),
    Measurement("holdout_calibrated_rotation_rms", "deg", "held out: RMS rotation error of the calibrated model"),
    Measurement("holdout_rms", "mm", "held out: RMS position error with the map"),
    Measurement("holdout_max", "mm", "held out: largest position error with the map"),
    Measurement("holdout_rotation_rms", "deg", "held out: RMS rotation error with the map"),
    Measurement("tracker_noise_rms", "mm", "the tracker's stated noise at the held-out distances (RMS)"),
    judged=("holdout_rms",))
@takes(HOLDOUT, SEED, TRACKER, GRID, SPAN, PAYLOAD, CALIBRATION, settings=(MESH,))
def checklist(s):
    s.connect()                                  # 1. connect and identify the robot (serial must match)
    s.check_state()                              # 2. no fault or stop, powered
    payload(s)                                   # 3. the payload on the tool, if any: the compliance terms
    calibration(s)                               #    the parametric calibration the map sits on, if any
    tracker = s.instrument("tracker")            #    connect and identify the tracker (journaled; same one)
    todo = map_plan(s)                           # 4. grid of actuator levels + held-out configurations
    for pose in s.todo(todo):                    # 5. every configuration not yet measured:
        move(s, pose)                            #    drive the actuators there (keep-outs checked)
        s.measure_pose(pose, tracker)            #    read actuators and tracker at rest, journal the sample
    reg = register_tracker(s)                    # 6. tracker frame -> base frame (best fit, grid samples only)
    cmap = build(s, reg)                         # 7. correction summands KSF_PM, the map KSF_KR
    verify(s, cmap, reg)                         # 8. held-out: nominal vs. mapped pose against the tracker
    store(s, cmap, reg)                          # 9. map.json in the session folder and in the record
    s.judge()                                    # 10. PASS / FAIL


# ---- the steps ---------------------------------------------------------------------------------------------
def map_plan(s) -> PosePlan:
    """The sample grid of the nominal model (``station.solver.map.plan``) in grid order, then the held-out
    configurations; journaled once (a resumed session reuses it)."""
    journaled = s.journaled_plan()
    if journaled is not None:
        return journaled
    with s.step("plan"):
        m = s.model
        try:
            q = int(s.options.get("grid", 2))
        except (TypeError, ValueError):
            raise ConfigError(f"correction_map: grid must be an integer Q, got {s.options.get('grid')!r}") from None
        mesh = str(s.options.get("mesh", "simplex"))
        lower, upper = work_box(s)
        try:
            p = plan(m, q, mesh=mesh, lower=lower, upper=upper)
        except ValueError as e:
            raise ConfigError(f"correction_map: {e}") from None
        if len(p.x) == 0:
            raise ConfigError(f"correction_map: none of the grid configurations of {m.name} can be assembled")
        predicted = None
        if _serial(m) and m.n_joints == 6:
            predicted = predicted_residual(m, p)
            if not predicted <= PREDICTED_LIMIT:
                raise ConfigError(
                    f"correction_map: the work box (joints +-{float(s.options.get('span_deg', 20.0)):g} deg around "
                    f"the current pose) comes too close to a singularity: a map there would leave "
                    f"{predicted:.0%} of a pose error (at most {PREDICTED_LIMIT:.0%}); jog the arm away from it "
                    f"(wrist centre off axis 1, elbow bent, wrist not straight) or give a smaller --span-deg")
        held = holdout_configurations(m, p, int(s.options.get("n_holdout", 12)), int(s.options.get("seed", 0)))
        x, clash = clear_of_keep_outs(s, p.x)
        held, _ = clear_of_keep_outs(s, held)
        if not len(x):
            raise ConfigError(f"correction_map: every grid configuration of {m.name} meets a keep-out")
        if clash:
            s.event(ev.Warn(step="plan", message=f"{clash} grid configurations left out: a link would meet the "
                                                 "mounting plane or a keep-out"))
        poses = [PlannedPose(i, "map", q.tolist(), q.tolist(), "fit") for i, q in enumerate(x)]
        poses += [PlannedPose(len(x) + i, "map", q.tolist(), q.tolist(), "holdout") for i, q in enumerate(held)]
        settings = {"generated": True, "map": {"grid": q, "mesh": mesh, "levels": [lv.tolist() for lv in p.levels],
                                               "left_out": len(p.dropped), "predicted_residual": predicted}}
        plan_ = PosePlan(poses, settings)
        s.event(ev.Plan(plan=plan_.to_dict()))
        if len(p.dropped):
            s.event(ev.Warn(step="plan", message=f"{len(p.dropped)} grid configurations left out (not assemblable "
                                                 "or too near the workspace boundary)"))
    s.current_plan = plan_
    return plan_


def work_box(s):
    """The actuator box the grid covers: a parallel robot's whole actuator range; a serial arm's joints
    +-``span_deg`` (default 20) around where the technician left it (jog it to the middle of the work zone
    first), inside the joint limits."""
    m = s.model
    if not _serial(m):
        return None, None
    span = np.radians(float(s.options.get("span_deg", 20.0)))
    q0 = np.asarray(s.robot.joint_positions().q, float)
    half = np.array([span if j.revolute else 0.1 for j in m.joints])  # prismatic: +-100 mm
    lo, hi = np.maximum(q0 - half, m.lower), np.minimum(q0 + half, m.upper)
    return lo, hi


def holdout_configurations(m, p, n: int, seed: int) -> np.ndarray:
    """``n`` random configurations inside the grid box (inset), off the grid nodes, that the nominal model
    assembles; seeded, so the plan is reproducible."""
    rng = np.random.default_rng(seed + 1004)
    lo = np.array([lv[0] for lv in p.levels])
    hi = np.array([lv[-1] for lv in p.levels])
    inset = HOLDOUT_INSET * (hi - lo)
    out = []
    for _ in range(50):
        if len(out) >= n:
            break
        cand = rng.uniform(lo + inset, hi - inset, (4 * n, m.n_joints))
        if getattr(m, "kind", "serial") == "parallel":
            cand = cand[m.fk_solve(cand).ok]
        out.extend(cand[: n - len(out)])
    return np.array(out[:n]).reshape(-1, m.n_joints)


def _serial(m) -> bool:
    return getattr(m, "kind", "serial") != "parallel"


def clear_of_keep_outs(s, x: np.ndarray) -> tuple[np.ndarray, int]:
    """A serial arm's configurations whose link capsules stay clear of the mounting plane and the cell's
    keep-outs (a parallel robot's legs have no capsules: all kept), and how many were left out."""
    if not _serial(s.model) or not len(x):
        return x, 0
    hits = s.checker().hits(x)
    keep = np.array([h is None for h in hits])
    return x[keep], int((~keep).sum())


@step(args=("pose",))
def move(s, pose: PlannedPose) -> None:
    """A serial arm moves along a path checked against the keep-outs (vias where the straight one is
    blocked; refused in one line if none is clear) and approaches every configuration from below on every
    joint (``APPROACH`` short of it first), so gear backlash sits on the same side at every sample; a parallel
    robot moves straight in actuator space."""
    if not _serial(s.model):
        s.move_to(pose.q)
        return
    m = s.model
    q = np.asarray(pose.q, float)
    short = np.maximum(q - np.array([APPROACH if j.revolute else APPROACH_LENGTH for j in m.joints]), m.lower)
    s.move_along([short, q], f"configuration {pose.index}")


def _arrays(s, which: str):
    smp = s.samples(which)
    if not smp:
        raise ConfigError(f"correction_map: no {which} samples recorded")
    if any(x.measured is None or x.measured_rotation is None for x in smp):
        raise ConfigError(f"correction_map: a {which} sample has no 6-DoF tracker measurement")
    x = np.array([x.q for x in smp])
    meas = np.array([[*x.measured, *x.measured_rotation] for x in smp])
    return x, meas


def register_tracker(s):
    """The tracker frame in the base frame, fitted on the grid samples: to the nominal model's tool frames
    (positions and orientations), or to a parametric calibration's tool POSITIONS only: a calibration is fitted
    on positions (``station solve`` on x,y,z), its orientation is not known better than nominal, and weighing
    it would tilt the frame (measured: held-out 0.149 mm calibrated-only with, 0.057 mm without; docs/map.md)."""
    with s.step("register_tracker"):
        x, meas = _arrays(s, "fit")
        model = working(s)
        if journaled_calibration(s) is None:
            reg = register(to_vectors(model.fk(x), FULL), meas, FULL)
        else:
            reg = register(model.fk(x)[:, :3, 3], meas[:, :3], POSITION)
        s.measure("registration_rms", reg.rms)
    return reg


def build(s, reg):
    with s.step("build_map"):
        x, meas = _arrays(s, "fit")
        cfg = (s.current_plan.settings or {}).get("map", {})
        levels = [np.asarray(lv, float) for lv in cfg["levels"]]
        try:
            cal = journaled_calibration(s)
            source = (s.events("calibration") or [None])[-1]
            cmap = build_map(s.model, x, reg.to_base(meas, FULL), FULL, mesh=cfg.get("mesh", "simplex"),
                             levels=levels, calibration=cal,
                             calibration_source=None if source is None else Path(source.data["path"]).name)
        except MapError as e:
            raise DeviceFault(f"correction_map: {e}") from None
        s.measure("samples", float(len(x)), "number")
        if cfg.get("predicted_residual") is not None:  # serial arms: the plan's singularity check (informational)
            s.measure("predicted_residual", float(cfg["predicted_residual"]), "number")
        big = np.asarray(cmap.statistics["summand_max"], float)  # largest correction per actuator (m or rad)
        rev = np.array([j.revolute for j in s.model.joints])
        if (~rev).any():
            s.measure("summand_max_length", float(np.max(big[~rev])))
        if rev.any():
            s.measure("summand_max_angle", float(np.max(big[rev])), "angle")
    return cmap


def verify(s, cmap, reg):
    """Held-out configurations: position error of the nominal model (and of the calibrated model alone, when
    the map sits on a calibration) and of the map's measuring kinematics DK(x - KSF(x)) against the tracker
    (registered to the base frame). Each model is compared in its own best-fit tracker frame (fitted on the grid
    samples only): a calibration moves the model's frames, and the tracker frame follows."""
    with s.step("verify"):
        x, meas = _arrays(s, "holdout")
        truth = reg.to_base(meas, FULL)
        nominal = to_vectors(s.model.fk(x), FULL)
        if journaled_calibration(s) is not None:  # the nominal model's own registration, for a fair "before"
            xf, mf = _arrays(s, "fit")
            nominal_truth = register(to_vectors(s.model.fk(xf), FULL), mf, FULL).to_base(meas, FULL)
        else:
            nominal_truth = truth
        try:
            mapped, _ = cmap.measure(s.model, x)
        except MapError as e:
            raise DeviceFault(f"correction_map: held-out {e}") from None
        e_nom = np.linalg.norm(nominal[:, :3] - nominal_truth[:, :3], axis=1)
        e_map = np.linalg.norm(mapped[:, :3] - truth[:, :3], axis=1)
        r_map = np.linalg.norm(se3.orientation_error(se3.rotvec_to_matrix(truth[:, 3:]),
                                                     se3.rotvec_to_matrix(mapped[:, 3:])), axis=1)
        s.measure("holdout", float(len(x)), "number")
        s.measure("holdout_nominal_rms", float(np.sqrt(np.mean(e_nom ** 2))))
        if journaled_calibration(s) is not None:  # what the parametric calibration alone gives: the map's baseline
            s.measure("calibration_parameters", float(len(journaled_calibration(s))), "number")
            cal_T = working(s).fk(x)
            e_cal = np.linalg.norm(cal_T[:, :3, 3] - truth[:, :3], axis=1)
            r_cal = np.linalg.norm(se3.orientation_error(se3.rotvec_to_matrix(truth[:, 3:]), cal_T[:, :3, :3]), axis=1)
            s.measure("holdout_calibrated_rms", float(np.sqrt(np.mean(e_cal ** 2))))
            s.measure("holdout_calibrated_max", float(np.max(e_cal)))
            s.measure("holdout_calibrated_rotation_rms", float(np.sqrt(np.mean(r_cal ** 2))), "angle")
            rc, rm = float(np.sqrt(np.mean(e_cal ** 2))), float(np.sqrt(np.mean(e_map ** 2)))
            if rm > rc:  # the map's interpolation error exceeds what it corrects in position: say so
                s.event(ev.Warn(step="verify", message=(
                    f"the map leaves more position error than the calibration alone on the held-out configurations "
                    f"({rm * 1e3:.3f} vs {rc * 1e3:.3f} mm RMS; orientation "
                    f"{np.degrees(np.sqrt(np.mean(r_map ** 2))):.4f} vs {np.degrees(np.sqrt(np.mean(r_cal ** 2))):.4f}"
                    f" deg): for positions use the calibration alone, or a finer --grid / smaller --span-deg")))
        s.measure("holdout_rms", float(np.sqrt(np.mean(e_map ** 2))))
        s.measure("holdout_max", float(np.max(e_map)))
        s.measure("holdout_rotation_rms", float(np.sqrt(np.mean(r_map ** 2))), "angle")
        # the instrument's own noise at these distances: 3-D RMS of one reflector reading (the floor); an
        # instrument that does not state its noise: nothing to compare with
        sig = s.instrument_sigma(np.linalg.norm(meas[:, :3], axis=1))
        if sig is not None:
            s.measure("tracker_noise_rms", float(np.sqrt(np.mean(3 * sig ** 2))))


def store(s, cmap, reg):
    import os

    with s.step("store_map"):
        path = s.folder / "map.json"
        tmp = path.with_name("map.json.tmp")
        with open(tmp, "w") as f:
            f.write(cmap.dumps())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        cal = (s.events("calibration") or [None])[-1]
        s.event({"type": "correction_map", "file": path.name, "registration": reg.to_dict(),
                 "calibration": None if cal is None else {k: cal.data.get(k) for k in
                                                          ("path", "sha256", "model", "parameters", "payload")},
                 "payload": s.options.get("payload"),
                 "map": json.loads(cmap.dumps())})
