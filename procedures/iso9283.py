"""ISO 9283 pose accuracy and repeatability with a laser tracker: AP, RP, vAP, AD and RD per pose, each with its
confidence interval, on the nominal model and (with ``--calibration``) on the calibrated one, side by side.

Technician: mount the 6-DoF probe on the tool, set the tracker up with a free line of sight to the working
area and give its address (``--tracker tcp://HOST:PORT``); jog the tool to the middle of the area of greatest
use, in the orientation the robot works in. The test cube is centred there, as large as the arm's reach, joint
limits and the cell's keep-outs allow (or ``--cube X,Y,Z,EDGE``); the tracker's frame is registered on eight
poses near the cube's corners; then ``--cycles N`` (default 30) cycles P1 > P5 > P4 > P3 > P2, every pose
approached from above (uni-directional: AP, RP, AD between P2 and P4), and N cycles of P1, P2, P4 approached
along +x and +y as well (multi-directional: vAP). Every reading is journaled before the next move, so a resumed
session measures only what is missing. Limits: ``procedures/limits.yaml``, section ``iso9283`` (the judged
figures are the worst pose's; with a calibration, those of the calibrated model). docs/iso9283.md says what
each figure means and how far it can be trusted."""

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
from station.engine.declare import Kind, Measurement, Option, choice, count, is_number, measures, takes
from station.engine.plan import PlannedPose, PosePlan
from station.engine.steps import step
from station.kinematics import se3
from station.performance import iso9283 as iso
from station.performance.cube import PLANES, CubeError, given_cube, largest_cube
from station.robot.errors import ConfigError
from station.solver.map import FULL, MapError, to_vectors
from station.solver.map.register import register

DEFAULTS = {"cycles": 30, "plane": "x+"}
UNI = "+z"  # AP, RP, AD: every pose approached from above
MULTI = ("+x", "+y")  # vAP: the same poses approached along the other two base axes as well
VAP_POSES = ("P1", "P2", "P4")
ORDER = ("P1", "P5", "P4", "P3", "P2")  # one cycle of the uni-directional test
PAIR = ("P2", "P4")  # distance accuracy: the two opposite poses
REGISTRATION_DRAWS = 200  # Monte Carlo refits of the tracker frame: its uncertainty at each pose
STATIC = 10  # readings of P1 without moving: the instrument's own scatter here (the floor under RP)

# the judged figures (the worst test pose's) and their quantity; with a calibration the nominal model's are
# measured too, as NAME_nominal
JUDGED = (("AP_p", "length"), ("RP_l", "length"), ("vAP_p", "length"), ("AD_p", "length"), ("RD_p", "length"),
          ("AP_abc", "angle"), ("RP_abc", "angle"), ("vAP_abc", "angle"))
FIGURES = {"AP": "pose accuracy", "RP": "pose repeatability", "vAP": "multi-directional pose accuracy variation",
           "AD": "distance accuracy", "RD": "distance repeatability"}


def _cube_value(text, flag: str, options: dict) -> list[float]:
    """``X,Y,Z,EDGE`` in the base frame, metres or one unit suffix for all (``400,0,500,300mm``), edge > 0 (SI)."""
    import math
    import re

    from station.units import LENGTH_UNITS

    m = re.match(r"^\s*([^,]+),([^,]+),([^,]+),([^,]+?)\s*([a-z]*)\s*$", str(text))
    if not m or (m.group(5) or "m") not in LENGTH_UNITS:
        raise ValueError
    v = [float(m.group(k)) * LENGTH_UNITS[m.group(5) or "m"] for k in range(1, 5)]
    if not all(math.isfinite(x) for x in v) or v[3] <= 0:
        raise ValueError
    return v


CYCLES = Option("cycles", "--cycles", count(4, 1000, "4..1000 cycles per pose (the standard: 30)"),
                "Cycles per pose (the standard's 30).", "count")
def _is_cube(v) -> bool:
    """A journaled cube: ``[x, y, z, edge]`` in metres, edge > 0."""
    return type(v) is list and len(v) == 4 and all(is_number(x, -1e9, 1e9) for x in v) and v[3] > 0


CUBE = Option("cube", "--cube", Kind("the centre and edge X,Y,Z,EDGE in the base frame (metres, or one unit for all: "
                                     "400,0,500,300mm), edge > 0", str, _cube_value, _is_cube,
                                     "[x, y, z, edge] in metres, edge > 0"),
              "The test cube's centre and edge X,Y,Z,EDGE in the base frame (e.g. 400,0,500,300mm).", "m",
              "the largest cube around the tool")
PLANE = Option("plane", "--plane", choice(*PLANES), "The cube's diagonal plane of the test poses: x+, x-, y+, y-, z+ "
               "or z-.")


def _figure(name: str, quantity: str, suffix: str = "", what: str = "") -> Measurement:
    unit = "mm" if quantity == "length" else "deg"
    axis = "position" if name.endswith(("_p", "_l")) else "orientation"
    return Measurement(name + suffix, unit, f"{FIGURES[name.split('_')[0]]} ({axis}) at the worst pose{what}")


@measures(
    Measurement("cycles", "count", "complete cycles per pose"),
    *(_figure(n, q) for n, q in JUDGED),
    *(_figure(n, q, "_nominal", ", nominal model (with --calibration)") for n, q in JUDGED),
    Measurement("AP_p_upper", "mm", "upper end of AP_p's confidence interval"),
    Measurement("RP_l_upper", "mm", "upper end of RP_l's confidence interval"),
    Measurement("rp_floor", "mm", "the instrument's own scatter at P1 (the floor under RP)"),
    Measurement("registration_rms", "mm", "RMS residual of the tracker frame's registration"),
    judged=("AP_p", "RP_l"))
@takes(TRACKER, CYCLES, CUBE, PLANE, PAYLOAD, CALIBRATION)
def checklist(s):
    s.connect()                                  # 1. connect and identify the robot (serial must match)
    s.check_state()                              # 2. no fault or stop, powered
    payload(s)                                   # 3. the payload on the tool, if any
    calibration(s)                               #    the calibration to evaluate besides the nominal model
    tracker = s.instrument("tracker")            # 4. connect and identify the tracker (journaled; same one)
    plan = test_plan(s)                          # 5. test cube, poses P1-P5, registration poses, cycles
    for pose in s.todo(plan):                    # 6. every pose not yet measured:
        approach(s, pose)                        #    to its approach pose, then onto it from that side
        s.measure_pose(pose, tracker)            #    joints and tracker at rest, journaled (fsynced)
    evaluate(s)                                  # 7. register the tracker, AP/RP/vAP/AD/RD per model
    s.judge()                                    # 8. PASS / FAIL by the limits


# ---- the plan --------------------------------------------------------------------------------------------
def _directions() -> dict[str, tuple[str, ...]]:
    return {"*": (UNI,), **{p: (UNI, *MULTI) for p in VAP_POSES}}


def _cycles(s) -> int:
    try:
        n = int(s.options.get("cycles", 30))
    except (TypeError, ValueError):
        n = 0
    if not 4 <= n <= 1000:
        raise ConfigError(f"iso9283: cycles must be an integer 4..1000 (the standard: 30), got "
                          f"{s.options.get('cycles')!r}")
    return n


def test_plan(s) -> PosePlan:
    """The test cube (largest around the tool, or ``--cube``), the joint values of every pose and approach pose,
    and the visiting order; journaled once (a resumed session reuses it)."""
    journaled = s.journaled_plan()
    if journaled is not None:
        return journaled
    with s.step("plan"):
        n = _cycles(s)
        checker = s.checker()
        q0 = np.asarray(s.robot.joint_positions().q, float)
        plane = str(s.options.get("plane", "x+"))
        try:
            cube = s.options.get("cube")
            if cube is not None:
                c = [float(v) for v in cube]
                cp = given_cube(s.model, q0, _directions(), c[:3], c[3], plane=plane, checker=checker)
            else:
                cp = largest_cube(s.model, q0, _directions(), plane=plane, checker=checker)
        except CubeError as e:
            raise ConfigError(f"iso9283: {e}") from None
        poses, series = [], []

        def visit(name: str, direction: str, label: str, cycle: int) -> None:
            poses.append(PlannedPose(len(poses), name, cp.poses[name].tolist(),
                                     cp.approach[name][direction].tolist(), "fit"))
            series.append([label, cycle, direction])

        for name in cp.cube.registration_positions():
            visit(name, UNI, "register", 0)
        for k in range(1, STATIC + 1):
            visit("P1", UNI, "static", k)
        for k in range(1, n + 1):
            for name in ORDER:
                visit(name, UNI, UNI, k)
        for d in MULTI:
            for k in range(1, n + 1):
                for name in VAP_POSES:
                    visit(name, d, d, k)
        settings = {"generated": True, "iso9283": {"cube": cp.cube.to_dict(), "cycles": n, "series": series,
                                                   "uni": UNI, "multi": list(MULTI), "pair": list(PAIR)}}
        plan = PosePlan(poses, settings)
        s.event(ev.Plan(plan=plan.to_dict()))
        c = cp.cube
        s.log(f"iso9283: test cube edge {c.edge * 1e3:.1f} mm at {', '.join(f'{v * 1e3:.1f}' for v in c.centre)} mm, "
              f"plane {c.plane}, {n} cycles, {len(poses)} poses")
    s.current_plan = plan
    return plan


@step(args=("pose",))
def approach(s, pose: PlannedPose) -> None:
    """To the pose's approach pose along a path clear of the keep-outs, then straight onto the pose: the last
    motion comes from the same side in every cycle, so the gears' backlash sits on the same side. The static
    readings after the first stay where the arm stands (it was approached for the first)."""
    label, k, _ = s.current_plan.settings["iso9283"]["series"][pose.index]
    here = np.asarray(s.robot.joint_positions().q, float)
    if label == "static" and k > 1 and np.max(np.abs(here - pose.q_arr)) < 1e-4:
        return
    s.check_space(f"the approach to pose {pose.index}")
    s.move_along([pose.approach_q, pose.q], f"pose {pose.index} ({pose.point})")


# ---- the evaluation --------------------------------------------------------------------------------------
def _series(s) -> dict:
    """The measured samples by role: registration ``[(q, reading)]`` and ``{(direction, pose): [(cycle, q,
    reading)]}`` (readings: x, y, z, rx, ry, rz in the instrument frame)."""
    meta = s.current_plan.settings["iso9283"]
    reg, cycles, static = [], {}, []
    for smp in s.samples():
        if smp.pose is None or smp.measured is None or smp.measured_rotation is None:
            continue
        label, k, d = meta["series"][smp.pose]
        reading = np.array([*smp.measured, *smp.measured_rotation])
        if label == "register":
            reg.append((np.asarray(smp.q, float), reading))
        elif label == "static":
            static.append(reading)
        else:
            cycles.setdefault((d, smp.point), []).append((k, s.current_plan.poses[smp.pose].q_arr, reading))
    return {"registration": reg, "cycles": {key: sorted(v, key=lambda r: r[0]) for key, v in cycles.items()},
            "static": np.array(static)}


def static_sigma(static: np.ndarray) -> float | None:
    """The instrument's per-axis scatter (1 sigma, m, RMS over the axes) from readings of a pose held still."""
    if len(static) < 3:
        return None
    return float(np.sqrt(np.mean(np.var(static[:, :3], axis=0, ddof=1))))


def _noise_cov(cycles: dict) -> np.ndarray:
    """Pooled within-pose covariance (6x6: position, rotation) of the uni-directional readings: the scatter of
    one reading (robot and instrument), which the registration readings carry too."""
    dev, dof = [], 0
    for (d, _), rows in cycles.items():
        if d != UNI or len(rows) < 2:
            continue
        m = np.array([r[2] for r in rows])
        R = se3.rotvec_to_matrix(m[:, 3:])
        mean_R = se3.rotvec_to_matrix(se3.matrix_to_rotvec(R).mean(axis=0))
        dev.append(np.column_stack([m[:, :3] - m[:, :3].mean(axis=0), se3.matrix_to_rotvec(R @ mean_R.T)]))
        dof += len(m) - 1
    if not dev:
        return np.zeros((6, 6))
    d = np.concatenate(dev)
    d[:, 3:] -= d[:, 3:].mean(axis=0)
    return d.T @ d / max(dof, 1)


def _frame_uncertainty(reg_q, reg_meas, model, cycles, noise: np.ndarray) -> tuple[dict, dict]:
    """Per uni-directional pose: the covariance (3x3 position, 3x3 rotation) its barycentre in the base frame
    gets from the tracker frame's fit, by refitting it on the registration readings with the readings' own
    scatter added (seeded: the same data give the same numbers)."""
    nominal = to_vectors(model.fk(reg_q), FULL)
    base = register(nominal, reg_meas, FULL)
    rng = np.random.default_rng(iso._seed(reg_meas))
    L = np.linalg.cholesky(noise + np.eye(6) * 1e-30)
    bary = {p: np.array([r[2] for r in rows]).mean(axis=0) for (d, p), rows in cycles.items() if d == UNI}
    shifts = {p: [] for p in bary}
    for _ in range(REGISTRATION_DRAWS):
        noisy = reg_meas.copy()
        e = rng.standard_normal((len(noisy), 6)) @ L.T
        noisy[:, :3] += e[:, :3]
        noisy[:, 3:] = se3.matrix_to_rotvec(se3.rotvec_to_matrix(e[:, 3:]) @ se3.rotvec_to_matrix(noisy[:, 3:]))
        r = register(nominal, noisy, FULL)
        for p, b in bary.items():
            v0 = base.to_base(b[None], FULL)[0]
            v1 = r.to_base(b[None], FULL)[0]
            rot = se3.matrix_to_rotvec(se3.rotvec_to_matrix(v1[3:]) @ se3.rotvec_to_matrix(v0[3:]).T)
            shifts[p].append(np.concatenate([v1[:3] - v0[:3], rot]))
    pos = {p: np.cov(np.array(v)[:, :3].T) for p, v in shifts.items()}
    rot = {p: np.cov(np.array(v)[:, 3:].T) for p, v in shifts.items()}
    return pos, rot


def evaluate_model(s, model, data: dict, noise: np.ndarray) -> tuple[dict, dict]:
    """The ISO figures with ``model`` computing the commanded poses (``FK(q commanded)``) and registering the
    tracker frame (best fit on the registration poses): ``(station-iso9283/1 result, registration)``."""
    reg_q = np.array([q for q, _ in data["registration"]])
    reg_meas = np.array([m for _, m in data["registration"]])
    try:
        reg = register(to_vectors(model.fk(reg_q), FULL), reg_meas, FULL)
    except MapError as e:
        raise ConfigError(f"iso9283: {e}") from None
    cycles = data["cycles"]
    commanded, attained, directions, sigma = {}, {}, {}, {}
    for (d, p), rows in cycles.items():
        meas = np.array([r[2] for r in rows])
        vec = reg.to_base(meas, FULL)
        if d == UNI:
            commanded[p] = to_vectors(model.fk(rows[0][1][None]), FULL)[0]
            attained[p] = vec
            sig = s.instrument_sigma(np.linalg.norm(meas[:, :3], axis=1).mean())
            sigma[p] = None if sig is None else float(sig)
        if p in VAP_POSES:
            directions.setdefault(p, {})[d] = vec
    sys_pos, sys_rot = _frame_uncertainty(reg_q, reg_meas, model, cycles, noise)
    for p, sig in sigma.items():  # the instrument's stated accuracy does not average out over cycles
        if sig is not None:
            sys_pos[p] = sys_pos[p] + np.eye(3) * sig ** 2
    held = static_sigma(data["static"])
    res = iso.evaluate({p: commanded[p] for p in ORDER if p in commanded}, attained,
                       directions={p: v for p, v in directions.items() if len(v) >= 2} or None,
                       pair=PAIR if all(p in attained for p in PAIR) else None, systematic=sys_pos,
                       systematic_rotation=sys_rot, instrument_sigma=held)
    if "instrument" in res:
        res["instrument"]["from"] = f"{len(data['static'])} readings of P1 held still"
    known = [v for v in sigma.values() if v is not None]
    if known:  # what the instrument states (one reading, per axis): the accuracy added to AP's interval
        res.setdefault("instrument", {})["stated_sigma_m"] = max(known)
    return res, reg.to_dict()



def evaluate(s) -> None:
    """Both models on the same readings: the nominal model (what the controller commands) and, with a
    calibration, the calibrated one; the judged figures are the calibrated model's when there is one."""
    with s.step("evaluate"):
        data = _series(s)
        if len(data["registration"]) < 3 or not data["cycles"]:
            raise ConfigError("iso9283: no measurements to evaluate")
        noise = _noise_cov(data["cycles"])
        cycles = min(len(v) for (d, _), v in data["cycles"].items() if d == UNI)
        models = {"nominal": s.model}
        if journaled_calibration(s) is not None:
            models["calibrated"] = working(s)
        results, regs = {}, {}
        for name, model in models.items():
            results[name], regs[name] = evaluate_model(s, model, data, noise)
        judged = "calibrated" if "calibrated" in results else "nominal"
        s.measure("cycles", float(cycles), "number")
        for name, quantity in JUDGED:
            for which, res in results.items():
                figure = res["summary"].get(name)
                if figure is None:
                    continue
                s.measure(name if which == judged else f"{name}_{which}", figure["value"], quantity)
        worst = results[judged]["summary"]
        for name in ("AP_p", "RP_l"):  # how sure: the top of the worst pose's interval (informational)
            if name in worst:
                s.measure(f"{name}_upper", worst[name]["ci"][1], "length")
        inst = results[judged].get("instrument")
        if inst:
            s.measure("rp_floor", inst["rp_floor_m"])
        s.measure("registration_rms", regs[judged]["rms_m"])
        cal = (s.events("calibration") or [None])[-1]
        s.event({"type": "iso9283", "judged": judged, "cube": s.current_plan.settings["iso9283"]["cube"],
                 "cycles": cycles, "approach": {"uni": UNI, "multi": list(MULTI), "vap_poses": list(VAP_POSES)},
                 "registration": regs, "results": results,
                 "calibration": None if cal is None else {k: cal.data.get(k) for k in ("path", "sha256", "model")}})
