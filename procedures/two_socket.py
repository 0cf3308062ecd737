"""Two sockets, one ball: the kinematics of a redundant arm from many arm configurations at two sockets a known
distance apart.

A ball on the flange is seated in each socket of a two-socket fixture from at least 20 configurations per
socket that vary the arm's null space (the elbow angle, joint 3 on a Franka, swept over its range at every tool
orientation) and the tool orientation, chosen D-optimally for the parameters to identify. Each seating is by
impedance (the arm compliant, the ball driven a few millimetres past the socket centre seats in the cone under
the arm's own control) and each sample is recorded on force contact (the robot's estimate of the external
force). The solve identifies the link geometry, joint zeros and the ball (``full``; a script passes
``options={"identify": "full,compliance"}`` for more) with both socket positions unknown and the fixture's
certified distance as a constraint (it fixes the length scale). Reported: the fit, the held-out consistency
(how closely the calibrated model puts every held-out touch of a socket on one point, mean distance from the
socket's centroid) and the distance error (the calibrated model's held-out socket centroids against the
certified distance); the calibrated model is exported as a URDF (and, with ``--apply``, through the robot's
own export). Limits: ``procedures/limits.yaml``, section ``two_socket``. Units: SI inside (m, rad); the cell
file states its own.

The protocol is the one of the best-known public ball-in-socket calibration data of Franka arms (a ball on the
flange, two sockets 50 mm apart, many configurations per socket)."""

import numpy as np

from station.engine import PlanError
from station.engine.declare import PLAN_OPTIONS, SOLVE, WRITE_BACK, Measurement, measures, takes
from station.engine.steps import step
from station.engine.touch import TouchFailed
from station.robot.capabilities import CalibrationExport, Compliant, ContactSensor
from station.robot.errors import ConfigError

IDENTIFY = "full"
DEFAULTS = {"per_socket": 20, "n_holdout": 8, "cone_deg": 35.0, "standoff_mm": 4.0, "press_mm": 5.0,
            "elbow_joint": 3, "settle_s": 5.0}
MIN_PER_SOCKET = 20


@measures(*SOLVE, *WRITE_BACK,
          Measurement("holdout_consistency", "mm", "calibrated model: mean distance of the held-out touches of a "
                      "socket from their centroid"),
          Measurement("nominal_consistency", "mm", "the same with the nominal model"),
          Measurement("distance_error", "mm", "calibrated model: held-out socket centroids' distance against the "
                      "certified one"),
          Measurement("nominal_distance_error", "mm", "the same with the nominal model"),
          judged=("fit_rms", "distance_error"))
@takes(*PLAN_OPTIONS)
def checklist(s):
    s.connect()                                  # 1. connect and identify (serial, the served model)
    s.check_state()                              # 2. no reflex or stop; not compliant
    plan = s.plan(listed=plan_poses(s), identify=s.options.get("identify", IDENTIFY))   # 3. >= 20 configurations
    #                                                per socket, null space varied
    for pose in s.todo(plan):                    # 4. every pose not yet recorded:
        s.approach(pose)                         #    above the socket, stiff
        seat_by_impedance(s, pose)               #    compliant, drive the ball past the centre: it seats
        s.record(pose)                           #    joints journaled while seated (force contact required)
        leave(s, pose)                           #    stiff again where it rests, back up to the approach pose
    s.solve(identify=s.options.get("identify", IDENTIFY))   # 5. geometry + zeros + ball, sockets unknown,
    #                                                             the certified distance as a constraint
    s.measure_result()                           # 6. fit, identified, held-out residuals
    measure_two_sockets(s)                       #    held-out consistency, distance error
    export_urdf(s)                               # 7. the calibrated URDF into the session folder
    s.judge()                                    # 8. PASS / FAIL
    s.write_back()                               # 9. with --apply: the robot's export (no kinematic write-back)


# ---- 3. the plan ---------------------------------------------------------------------------------------------
def plan_poses(s):
    """Listed poses (``s.plan(listed=...)``): per socket ``per_socket`` fit and ``n_holdout / sockets``
    held-out configurations, D-optimal for the parameters to identify and both socket positions among
    candidates that sweep the elbow joint over its range at tool orientations inside a cone about the
    socket's approach axis. None when the journal already holds the plan (a resumed session keeps it)."""
    if s.events("plan"):
        return None
    model, opt = s.model, s.options
    if model.n_joints != 7:
        raise ConfigError(f"two_socket is for 7-DOF arms; model {model.name} has {model.n_joints} joints")
    sockets = s.points("socket")
    if len(sockets) != 2:
        raise ConfigError(f"two_socket needs exactly two sockets in the cell, found {len(sockets)}: "
                          f"{', '.join(p.label for p in sockets) or 'none'}")
    labels = {p.label for p in sockets}
    if not any({a, b} == labels for a, b, *_ in s.cell.distances):
        raise ConfigError(f"two_socket: the cell states no distance between {' and '.join(sorted(labels))} "
                          "(distances: [{between: [A, B], distance: 50.0}]); without it the scale is not observable")
    per = int(opt.get("per_socket", DEFAULTS["per_socket"]))
    if "n_fit" in s.given:
        per = int(opt["n_fit"]) // 2
    if per < MIN_PER_SOCKET:
        raise ConfigError(f"two_socket: {per} fit configurations per socket; at least {MIN_PER_SOCKET}")
    hold = int(opt.get("n_holdout", DEFAULTS["n_holdout"])) // 2
    identify = opt.get("identify", IDENTIFY)
    names = [n for n in model.select(identify) if not n.startswith("compliance.")]
    rng = np.random.default_rng(int(opt.get("seed", 0)))
    q0 = s.robot.joint_positions().q
    entries = []
    for k, pt in enumerate(sockets):
        Q = _candidates(s, pt, q0, rng, float(opt.get("cone_deg", DEFAULTS["cone_deg"])),
                        int(opt.get("elbow_joint", DEFAULTS["elbow_joint"])) - 1)
        if len(Q) < per + hold:
            raise PlanError(f"two_socket: socket {pt.label}: {len(Q)} reachable configurations clear of the "
                            f"keep-outs, {per + hold} wanted; move the fixture or widen the cone (--cone)")
        rows = _rows(model, Q, names, k)
        picked = _d_optimal(rows, per + hold)
        spread = Q[picked]
        for i, q in enumerate(spread):
            entries.append({"point": pt.label, "q": q.tolist(), "set": "fit" if i < per else "holdout"})
    return entries


def _candidates(s, pt, q0, rng, cone_deg, elbow, n_orient=40, n_elbow=7):
    """Touch configurations of socket ``pt``: tool z inside the cone about the inward approach axis, a random
    roll, and the elbow joint held at ``n_elbow`` values across its range (IK of the other six joints for the
    full pose); those within the limits (10 deg margin) whose pose, approach pose and path between keep every
    link clear of the cell's keep-outs."""
    from station.engine.plan import _cone_dirs
    from station.kinematics.collision import Checker, KeepOut
    from station.kinematics.se3 import frame_with_z

    model = s.model
    lo, hi = model.lower, model.upper
    margin = np.deg2rad(10.0)
    dirs = _cone_dirs(-pt.approach, np.deg2rad(cone_deg), n_orient, rng)
    rolls = rng.uniform(-np.pi, np.pi, n_orient)
    elbows = np.linspace(lo[elbow] + margin, hi[elbow] - margin, n_elbow)
    T = np.repeat(np.eye(4)[None], n_orient * n_elbow, axis=0)
    seeds = np.repeat(np.clip(q0, lo + margin, hi - margin)[None], n_orient * n_elbow, axis=0)
    for i in range(n_orient):
        for j in range(n_elbow):
            r = i * n_elbow + j
            T[r, :3, :3] = frame_with_z(dirs[i], rolls[i])
            T[r, :3, 3] = pt.position
            seeds[r, elbow] = elbows[j]
    W = np.ones(model.n_joints)
    W[elbow] = 0.0  # the elbow stays where the seed puts it: the null space is swept, not left to the IK
    res = model.ik(T, seeds, weights=W, max_iter=200)
    ok = res.ok & np.all((res.q >= lo + margin) & (res.q <= hi - margin), axis=1)
    Q = res.q[ok]
    if not len(Q):
        return Q
    back = T[ok].copy()
    back[:, :3, 3] += pt.approach * float(s.options.get("clearance", 0.03))
    ra = model.ik(back, Q, weights=W, max_iter=100)
    keep = ra.ok & (np.max(np.abs(ra.q - Q), axis=1) < 0.3)
    checker = Checker(model, s.cell.keep_out if s.cell else KeepOut.default())
    keep &= checker.clear(Q) & checker.clear(ra.q)
    Q, QA = Q[keep], ra.q[keep]
    if len(Q):
        clear = checker.paths_clear(QA, Q)
        Q = Q[clear]
    return Q


def _rows(model, Q, names, k):
    """Identification rows (N, 3, P + 6): model parameters, then -I for socket ``k`` of the two."""
    J = model.jacobian_params(Q, names=names)[:, :3, :]
    E = np.zeros((len(Q), 3, 6))
    E[:, :, 3 * k:3 * k + 3] = -np.eye(3)
    return np.concatenate([J, E], axis=2)


def _d_optimal(rows, k):
    """Greedy D-optimal choice of ``k`` candidates (scaled columns, a small ridge for what one socket cannot
    show)."""
    N, _, P = rows.shape
    scale = np.linalg.norm(rows.reshape(-1, P), axis=0)
    scale[scale < 1e-12] = 1.0
    A = rows / scale
    M = np.eye(P) * 1e-6 * N
    free = np.ones(N, bool)
    chosen = []
    for _ in range(min(k, N)):
        G = np.einsum("nip,pq,njq->nij", A, np.linalg.inv(M), A)
        gain = np.linalg.slogdet(np.eye(3)[None] + G)[1]
        gain[~free] = -np.inf
        i = int(np.argmax(gain))
        chosen.append(i)
        free[i] = False
        M = M + A[i].T @ A[i]
    return chosen


# ---- 4. seating by impedance ---------------------------------------------------------------------------------
def _along(s, point, q, depth):
    """Joint target with the tool ``depth`` m further along the inward approach axis of socket ``point`` (same
    orientation, elbow held)."""
    model = s.model
    T = model.fk(q)
    T[:3, 3] -= point.approach * depth
    W = np.ones(model.n_joints)
    W[int(s.options.get("elbow_joint", DEFAULTS["elbow_joint"])) - 1] = 0.0
    r = model.ik(T, q, weights=W)
    if not r.ok[0]:
        raise TouchFailed(f"socket {point.label}: no joint solution {depth * 1e3:+.1f} mm along the approach")
    return r.q[0]


@step("seat", args=("pose",))
def seat_by_impedance(s, pose):
    """From the approach pose: stiff to ``standoff_mm`` above where the model puts the socket (corrected by the
    earlier seatings there), compliant; a robot that presses on by itself when it turns compliant (a Franka:
    ``press_force`` along the approach) has then seated the ball. Otherwise drive ``press_mm`` past the centre;
    the ball seats in the cone and the arm comes to rest against it. Done when the robot senses the contact
    force and stands still; without contact the target goes ``press_mm`` deeper, twice (the cell's socket
    positions are approximate)."""
    import time

    robot = s.robot
    if not (isinstance(robot, Compliant) and isinstance(robot, ContactSensor)):
        raise ConfigError("two_socket seats by impedance and records on force contact: the robot needs a compliant "
                          "mode and contact sensing (a Franka arm: franka://)")
    s.check_space(f"seating at pose {pose.index}")
    point = s.point(pose.point)
    opt = s.options
    standoff = float(opt.get("standoff_mm", DEFAULTS["standoff_mm"])) * 1e-3
    step = float(opt.get("press_mm", DEFAULTS["press_mm"])) * 1e-3
    settle = float(opt.get("settle_s", DEFAULTS["settle_s"]))
    target = s.aimed_q(pose)
    stand = _along(s, point, target, -standoff)
    robot.move_joints(stand, speed=s.touch_speed(pose.approach_arr, stand))
    if robot.touch():
        raise TouchFailed(f"pose {pose.index}: contact {standoff * 1e3:g} mm before socket {pose.point}: check the "
                          "cell file")
    robot.set_compliant(True)
    if robot.touch() and not robot.status().moving:
        return  # the robot pressed on along the approach itself and the ball rests in the cone (a Franka's
        # seating press, docs/hardware-franka.md): driving the target elsewhere would only change the push
    here = stand
    for depth in (step, 2 * step, 3 * step):
        press = _along(s, point, target, depth)
        robot.move_joints(press, speed=s.touch_speed(here, press))
        here = press
        end = time.monotonic() + settle
        while time.monotonic() < end:
            if robot.touch() and not robot.status().moving:
                return
            time.sleep(0.01)
            if not robot.status().moving and not robot.touch():
                break  # at rest without contact: deeper
    robot.set_compliant(False)
    raise TouchFailed(f"pose {pose.index}: no contact force in socket {pose.point} down to {3 * step * 1e3:g} mm past "
                      "where the model puts it (socket elsewhere? check the cell file)")


@step(args=("pose",))
def leave(s, pose):
    """Stiff again where the ball rests (the robot holds it there: the push is gone), then straight back up to
    the approach pose."""
    s.robot.set_compliant(False)
    s.robot.move_joints(pose.approach_arr)


# ---- 6. what the two sockets show ----------------------------------------------------------------------------
def measure_two_sockets(s):
    """Held-out consistency (calibrated model: mean distance of each held-out touch from its socket's centroid,
    averaged over the sockets) and the distance error (|distance of the two held-out centroids - certified|);
    each also for the nominal model, informational."""
    res = s.result
    held = s.samples("holdout") or s.samples("fit")
    if not held:
        raise ConfigError("two_socket: no samples to judge")
    cal = res.calibrated(s.model)
    q = np.array([x.q for x in held])
    point = np.array([x.point for x in held], dtype=object)
    out = []
    for name, model in (("holdout_consistency", cal), ("nominal_consistency", s.model)):
        P = model.position(q)
        spread, centre = [], {}
        for label in dict.fromkeys(point.tolist()):
            p = P[point == label]
            centre[label] = p.mean(axis=0)
            spread.append(float(np.mean(np.linalg.norm(p - centre[label], axis=1))))
        out.append(s.measure(name, float(np.mean(spread))))
        a, b, d, _ = next(x for x in s.cell.distances if {x[0], x[1]} <= set(centre))
        err = abs(float(np.linalg.norm(centre[a] - centre[b])) - d)
        out.append(s.measure("distance_error" if model is cal else "nominal_distance_error", err))
    return out


# ---- 7. the calibrated URDF ----------------------------------------------------------------------------------
def export_urdf(s):
    """The calibrated model as a URDF (joint origins hold the identified geometry and zeros; the ball is the tool
    link) and as a station model file, in the session folder; journaled as an ``export`` event."""
    from station.kinematics.modelfile import dump_model
    from station.kinematics.urdfexport import urdf_text

    cal = s.result.calibrated(s.model)
    folder = s.folder
    urdf = folder / f"{s.model.name}_calibrated.urdf"
    urdf.write_text(urdf_text(cal, note=f"calibrated by station session {s.id} (two_socket)"), encoding="utf-8")
    yml = folder / f"{s.model.name}_calibrated.yaml"
    yml.write_text(dump_model(cal), encoding="utf-8")
    s.event({"type": "export", "files": [str(urdf), str(yml)],
             "note": "calibrated model; the robot is unchanged" if isinstance(s.robot, CalibrationExport) else
             "calibrated model"})
    return [urdf, yml]
