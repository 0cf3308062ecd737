"""Where an arm of one's own can reach a calibration cell: reference points computed from the model's workspace.

``station mock world example --model myarm.urdf`` has no hand-placed cell for an arm it has never seen. A socket
is useful only where the tool reaches it from a wide cone of orientations (the zero offsets and the link
geometry are seen through the spread of poses), inside the joint limits with a margin, with every link clear of
the mounting plane and the keep-outs (the station's link capsules, the station's 10 mm clearance), including
the last 30 mm of the approach. Candidate points on rings around joint 1's axis at several heights are scored by
the fraction of tool directions in a 35 deg cone (and rolls about the tool axis) that inverse kinematics reaches
so; the best are kept, spread apart (``dh_full`` needs three sockets spread over the workspace). Pure numpy, no
I/O; deterministic for a seed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.kinematics.se3 import frame_with_z

CONE = np.deg2rad(35.0)  # the pose plan's default cone (station.engine.plan)
MARGIN = np.deg2rad(5.0)  # the pose plan's joint-limit margin
CLEARANCE = 0.03  # m: the approach pose backs off this far along the approach direction
MIN_SCORE = 0.4  # at least this fraction of the cone's directions reachable clear: a useful socket


@dataclass
class Placement:
    points: list[dict]  # {label, kind, position [m], approach, score}
    start: list[float]  # encoder positions at power-on: the tool above the first socket, pointing down
    reach: float  # m: the tool's largest distance from joint 1's axis (sampled)
    note: str = ""  # why there are fewer points than asked, when there are


def _directions() -> list[tuple[np.ndarray, float]]:
    """Tool z axes in the cone around straight down and rolls about them (the cone the plan draws from)."""
    out = [(np.array([0.0, 0.0, -1.0]), 0.0), (np.array([0.0, 0.0, -1.0]), np.pi / 2)]
    for tilt in (0.6 * CONE, CONE):
        for k, az in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False)):
            d = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
            out.append((d, (k % 3 - 1) * np.pi / 3))
    return out


def _limits(model) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.maximum(model.lower, -np.pi), np.minimum(model.upper, np.pi)
    return lo, hi


def _inside(model, q: np.ndarray) -> np.ndarray:
    m = np.array([MARGIN if j.revolute else 0.005 for j in model.joints])
    return np.all((q >= model.lower + m) & (q <= model.upper - m), axis=1)


def workspace_reach(model, rng, n: int = 3000) -> tuple[float, float, np.ndarray]:
    """(largest distance of the tool from joint 1's axis, height of joint 2's origin, sample of tool positions)
    over random configurations inside the limits."""
    lo, hi = _limits(model)
    Q = lo + (hi - lo) * rng.random((n, model.n_joints))
    P = model.position(Q)
    axis_origin = model.position(np.zeros((1, model.n_joints)))[0] * 0.0  # joint 1's axis through the base origin
    r = np.hypot(P[:, 0] - axis_origin[0], P[:, 1] - axis_origin[1])
    return float(np.quantile(r, 0.98)), float(np.median(P[:, 2])), P


def cone_scores(model, positions, keep_out=None, *, approach=(0.0, 0.0, 1.0), seed: int = 0, tries: int = 12):
    """For each point (M, 3): the fraction of the cone's tool directions the nominal model reaches inside its
    limits (5 deg margin) with every link clear of ``keep_out`` (None: the mounting plane z = 0, 10 mm) on the
    touch pose, the approach pose 30 mm back and the path between; and the touch configurations (M, D, n),
    NaN where not reached."""
    from station.kinematics.collision import Checker, KeepOut

    rng = np.random.default_rng(seed)
    model = _rigid(model)
    keep_out = KeepOut.default() if keep_out is None else keep_out
    checker = Checker(model, keep_out)
    cand = np.atleast_2d(np.asarray(positions, float))
    up = np.asarray(approach, float)
    dirs = _directions()
    n_dir = len(dirs)
    R = np.stack([frame_with_z(d, roll) for d, roll in dirs])
    T = np.repeat(np.eye(4)[None], len(cand) * n_dir, axis=0)
    T[:, :3, :3] = np.tile(R, (len(cand), 1, 1))
    T[:, :3, 3] = np.repeat(cand, n_dir, axis=0)
    # straight down first, from a few random seeds; every other direction of the cone continues from that
    # solution (the same arm configuration tilted): a fraction of the solves random seeds would need
    lo, hi = _limits(model)
    down = np.arange(len(cand)) * n_dir
    q_down = np.full((len(cand), model.n_joints), np.nan)
    for _ in range(tries):
        todo = np.flatnonzero(np.isnan(q_down[:, 0]))
        if not len(todo):
            break
        res = model.ik(T[down[todo]], lo + (hi - lo) * rng.random((len(todo), model.n_joints)), max_iter=120)
        good = res.ok & _inside(model, res.q)
        good[good] = checker.clear(res.q[good])  # not the elbow through the table: the cone continues from it
        q_down[todo[good]] = res.q[good]
    have = np.flatnonzero(~np.isnan(q_down[:, 0]))
    rows = (have[:, None] * n_dir + np.arange(n_dir)[None]).ravel()
    best_q = np.full((len(T), model.n_joints), np.nan)
    if len(rows):
        res = model.ik(T[rows], np.repeat(q_down[have], n_dir, axis=0), max_iter=120)
        good = res.ok & _inside(model, res.q)
        back = T[rows[good]].copy()
        back[:, :3, 3] += up * CLEARANCE
        ra = model.ik(back, res.q[good], max_iter=80)
        qt, qa = res.q[good], ra.q
        fine = ra.ok & _inside(model, qa) & (np.max(np.abs(qa - qt), axis=1) < 0.6)
        qt, qa, idx = qt[fine], qa[fine], rows[good][fine]
        clear = checker.clear(qt) & checker.clear(qa)
        if clear.any():
            clear[clear] = checker.paths_clear(qa[clear], qt[clear])
        best_q[idx[clear]] = qt[clear]
    best_q = best_q.reshape(len(cand), n_dir, model.n_joints)
    return (~np.isnan(best_q[:, :, 0])).mean(axis=1), best_q


def place_points(model, keep_out=None, *, seed: int = 0, sockets: int = 3, needles: int = 1,
                 approach=(0.0, 0.0, 1.0), fixed=()) -> Placement:
    """Reference points an arm of one's own reaches from a wide cone, clear of the mounting plane and the
    keep-outs, spread apart (also from the ``fixed`` positions already in the cell); and a start pose above the
    first one. ``keep_out``: a ``KeepOut`` (None: the mounting plane z = 0 with the station's clearance)."""
    from station.kinematics.collision import Checker, KeepOut

    rng = np.random.default_rng(seed)
    model = _rigid(model)
    keep_out = KeepOut.default() if keep_out is None else keep_out
    reach, _, P = workspace_reach(model, rng)
    up = np.asarray(approach, float)
    floor = keep_out.mounting.offset if keep_out.mounting is not None else float(np.min(P[:, 2]))
    heights = floor + np.array([0.05, 0.12, 0.25, 0.45, 0.65]) * max(reach, 0.2)
    radii = np.array([0.4, 0.55, 0.7]) * reach
    azimuths = np.linspace(-np.pi, np.pi, 8, endpoint=False)
    cand = np.array([[r * np.cos(a), r * np.sin(a), z] for z in heights for r in radii for a in azimuths])
    score, best_q = cone_scores(model, cand, keep_out, approach=up, seed=seed)
    # the best cone first, then the lower fixture (a table), then in front of the arm (+x); the next points as
    # far from the chosen ones as the good candidates allow (link geometry shows in the spread)
    azimuth = np.abs(np.arctan2(cand[:, 1], cand[:, 0]))
    order = np.lexsort((azimuth, cand[:, 2], -np.round(score, 2)))
    good = [int(i) for i in order if score[i] >= max(MIN_SCORE, 0.9 * score[order[0]])]
    if good:  # one side of the arm, as a cell on a table in front of it: turning joint 1 half a turn between
        ref = np.asarray(fixed[0], float) if len(fixed) else cand[good[0]]  # two sockets is travel, not information
        front = np.arctan2(ref[1], ref[0])
        good = [i for i in good if abs(np.angle(np.exp(1j * (np.arctan2(cand[i, 1], cand[i, 0]) - front))))
                <= np.deg2rad(100)]
    taken = [np.asarray(f, float) for f in fixed]
    chosen: list[int] = []
    while good and len(chosen) < sockets + needles:
        pick = good[0] if not taken else max(good, key=lambda i: min(np.linalg.norm(cand[i] - t) for t in taken))
        if taken and min(np.linalg.norm(cand[pick] - t) for t in taken) < 0.15 * reach:
            break
        chosen.append(pick)
        taken.append(cand[pick])
        good.remove(pick)
    points = []
    for k, i in enumerate(chosen):
        kind = "socket" if k < sockets else "needle"
        label = "ABCDEFGH"[k] if kind == "socket" else ("N" if k == sockets else f"N{k - sockets + 1}")
        points.append({"label": label, "kind": kind, "position": [round(float(x), 3) for x in cand[i]],
                       "approach": [float(a) for a in up], "score": float(score[i])})
    start = _start_above(model, Checker(model, keep_out), best_q[chosen[0]] if chosen else None, up)
    note = ""
    if len(points) < sockets + needles:
        note = (f"only {len(points)} of {sockets + needles} points reach a {np.degrees(CONE):.0f} deg cone clear of "
                "the mounting plane and keep-outs")
    return Placement(points, start, reach, note)


def _rigid(model):
    """The model without its gravity load when no joint is compliant: the same kinematics, and the fused chain's
    fast path for IK (a URDF with <inertial> masses carries a load even when its compliance is zero)."""
    from dataclasses import replace

    js, ps = model.compliance_index
    if getattr(model, "load", None) is None or (len(ps) and model.params[ps].any()):
        return model
    return replace(model, load=None)


def _wrap(model, q: np.ndarray) -> list[float]:
    """Each revolute angle in (-180, 180] deg where the limits allow: a start pose as a person writes it."""
    q = np.array(q, float)
    for j, jt in enumerate(model.joints):
        if jt.revolute:
            w = (q[j] + np.pi) % (2 * np.pi) - np.pi
            if jt.lower <= w <= jt.upper:
                q[j] = w
    return [float(x) for x in q]


def _start_above(model, checker, qs, up) -> list[float]:
    """The tool 150 mm above the first point, pointing down: where an arm stands over its cell at power-on (the
    straight-down solution moved up by IK, inside the limits and clear; else the touch pose itself)."""
    if qs is None or np.isnan(qs[0]).any():
        return _wrap(model, np.clip(np.zeros(model.n_joints), model.lower, model.upper))
    q = qs[0]
    T = model.fk(q[None])
    T[:, :3, 3] += up * 0.15
    r = model.ik(T, q[None], max_iter=120)
    if r.ok[0] and _inside(model, r.q)[0] and checker.clear(r.q)[0] and checker.paths_clear(r.q, q[None])[0]:
        return _wrap(model, r.q[0])
    return _wrap(model, q)
