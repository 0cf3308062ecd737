# ruff: noqa: E402  (BLAS thread count must be set before numpy is imported)
"""Correction-map benchmark (docs/map.md): held-out position error before/after on the seed's planar robot and the
hexapod with hidden geometric errors, parametric vs map vs both on a 6R arm with compliance and backlash, error
vs number of samples (grid vs simplex), build and lookup time, (e) the 6R arm in the correction_map
procedure's work boxes: a bent-elbow box vs one at the shoulder singularity (the plan's predicted residual), and
(f) the procedure's bent-elbow box with compliance and backlash: parametric vs map vs both, Q = 1 and 2, with
and without a compliance term in the parametric calibration.

The truth is the simulated world (station.mocks.world): its true model, joint compliance under a payload and
backlash. "Before" commands the nominal inverse kinematics; "after" commands the map's calibrated control.
Held-out targets are poses the true robot reaches at random actuator values (1 % inside the limits), never
sample configurations.

Run: .venv/bin/python bench/map.py [--quick] [--parts abcdef]"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from station.mocks.world import World
from station.mocks.world.tracker import measure_points, measure_poses
from table import print_table

from station.kinematics import dump_model, load_model, se3
from station.solver import Observations, solve
from station.solver.map import FULL, build_map, plan, to_vectors

TRACKER = np.array([[0, -1, 0, 2.5], [1, 0, 0, 0.0], [0, 0, 1, 1.0], [0, 0, 0, 1]], dtype=float)  # 2.7 m away
REFLECTORS = np.array([[0.10, 0, 0.02], [-0.05, 0.0866, 0.02], [-0.05, -0.0866, 0.02]])  # 6-DoF probe on the tool


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def um(v: float) -> str:
    return f"{v * 1e6:.1f}"


def measure(T, planar: bool, noise: bool, rng):
    """What the instrument gives, in the robot base frame (its registration assumed known here)."""
    if noise and planar:  # one reflector on the hinge
        p = measure_points(T[:, :3, 3], TRACKER, rng)
        return (p @ TRACKER[:3, :3].T + TRACKER[:3, 3])[:, :2]
    if noise:
        T = TRACKER @ measure_poses(T, REFLECTORS, TRACKER, rng)
    return T[:, :2, 3].copy() if planar else to_vectors(T, FULL)


def held_out(world, n: int, rng):
    nom = world.nominal
    q = nom.lower + (nom.upper - nom.lower) * (0.01 + 0.98 * rng.uniform(0, 1, (n, nom.n_joints)))
    res = world.truth.fk_solve(q, guess=nom.fk_solve(q).T)
    return res.T[res.ok]


def parallel_case(world, label: str, q: int, mesh: str, rng, noise: bool = False, n_held: int = 1000) -> dict:
    nom, truth = world.nominal, world.truth
    planar = nom.type == "planar-struts"
    cols = ("x", "y") if planar else FULL
    p = plan(nom, q, mesh=mesh)
    reached = truth.fk_solve(p.x, guess=nom.fk(p.x))
    x = p.x[reached.ok]
    meas = measure(reached.T[reached.ok], planar, noise, rng)
    t0 = time.perf_counter()
    cm = build_map(nom, x, meas, cols, mesh=mesh)
    t_build = time.perf_counter() - t0
    P = held_out(world, n_held, rng)
    target = P[:, :2, 3] if planar else to_vectors(P, FULL)
    k = 2 if planar else 3
    before = np.linalg.norm(truth.fk(nom.ik_closed(P, check_limits=False)[0], guess=P)[:, :k, 3] - P[:, :k, 3], axis=1)
    t0 = time.perf_counter()
    c, _ = cm.command(nom, target, cols)
    t_cmd = (time.perf_counter() - t0) / len(c)
    after = np.linalg.norm(truth.fk(c, guess=P)[:, :k, 3] - P[:, :k, 3], axis=1)
    xq = rng.uniform(nom.lower, nom.upper, (100000, nom.n_joints))
    t_look = lookup_seconds(cm, xq)
    return {"robot": label, "Q": q, "mesh": mesh, "meas.": "tracker" if noise else "exact", "samples": len(x),
            "left out": len(p.dropped) + int((~reached.ok).sum()), "held-out": len(P),
            "before RMS um": um(rms(before)), "after RMS um": um(rms(after)), "after max um": um(after.max()),
            "reduction": f"{100 * (1 - rms(after) / rms(before)):.2f}%", "build ms": f"{t_build * 1e3:.0f}",
            "lookup us/q": f"{t_look * 1e6:.2f}", "command us": f"{t_cmd * 1e6:.0f}"}


def lookup_seconds(cm, xq, repeats: int = 3) -> float:
    """Best of ``repeats`` (the machine is shared) wall time per query of one vectorised KSF_KR lookup."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        cm.summand(xq)
        best = min(best, time.perf_counter() - t0)
    return best / len(xq)


def wide_hexapod(seed: int, folder: Path) -> World:
    """The built-in hexapod with a 150 mm stroke (450..600 mm): tilts up to ~75 deg, unassemblable corners."""
    import yaml

    doc = yaml.safe_load(dump_model(load_model("hexapod"), "mm", "deg"))
    doc["name"] = "hexapod-wide"
    doc["parallel"]["legs"]["limits"] = [450, 600]
    path = folder / "hexapod-wide.yaml"
    path.write_text(yaml.safe_dump(doc))
    return World.default(str(path), seed=seed)


def part_a(quick: bool, rng) -> None:
    print("(a) held-out position error, nominal control (before) vs calibrated control with the map (after); "
          "hexapod: World.default hidden errors (anchors 0.2 mm, leg offsets 0.1 mm, tool 0.5 mm sigma);\n"
          "    planar: pivots/strut offsets 0.3 mm sigma; tracker: +-(15 um + 6 um/m) per reflector as 1 sigma, "
          "2.7 m away, 3-reflector 6-DoF probe")
    rows = []
    struts = World.from_dict({"format": "station-world/1", "units": {"length": "mm", "angle": "deg"}, "seed": 1,
                              "robot": {"model": "struts2"}, "errors": {"random": {"pivots": 0.3, "offsets": 0.3}}})
    for q in (1, 2, 4):
        for mesh in ("grid", "simplex"):
            rows.append(parallel_case(struts, "struts2 (seed)", q, mesh, rng))
    rows.append(parallel_case(struts, "struts2 (seed)", 4, "grid", rng, noise=True))
    seeds = (0,) if quick else (0, 1, 2)
    for s in seeds:
        w = World.default("hexapod", seed=s)
        for mesh in ("grid", "simplex"):
            rows.append(parallel_case(w, f"hexapod seed {s}", 2, mesh, rng))
    w = World.default("hexapod", seed=0)
    rows.append(parallel_case(w, "hexapod seed 0", 2, "simplex", rng, noise=True))
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        rows.append(parallel_case(wide_hexapod(0, Path(tmp)), "hexapod 450..600", 2, "simplex", rng))
    print_table(rows)


def arm_world(seed: int) -> World:
    return World.default("arm6", seed=seed, joints={"compliance": {"j2": 2e-5, "j3": 3e-5, "j5": 4e-5},
                                                    "backlash": {"j1": 3e-4, "j2": 3e-4, "j3": 3e-4}, "payload": 15.0})


BOX_LO = np.radians([-20, -10, -10, -30, -70, -30])
BOX_HI = np.radians([20, 30, 30, 30, -30, 30])


def part_b(quick: bool, rng) -> None:
    print("\n(b) 6R arm (arm6) with hidden geometry (World.default sigmas), gravity compliance (15 kg payload on j2, "
          "j3, j5) and backlash (0.017 deg on j1-j3);\n    work box j1 +-20, j2 -10..30, j3 -10..30, j4 +-30, j5 "
          "-70..-30, j6 +-30 deg; exact pose measurements; every move approaches from below unless stated")
    w = arm_world(3)
    nom = w.nominal

    def reach(x, side=None):
        out = []
        for i, xi in enumerate(np.atleast_2d(x)):
            s = 1.0 if side is None else side[i]
            w.command_q(xi - s * 0.01)
            w.command_q(xi)
            out.append(w.tip_pose_true())
        return np.array(out)

    n_cal = 60
    qc = BOX_LO + (BOX_HI - BOX_LO) * rng.uniform(0, 1, (n_cal, 6))
    t0 = time.perf_counter()
    res = solve(nom, Observations(qc, np.full(n_cal, "A", dtype=object), reach(qc)[:, :3, 3]), "offsets,dh,tcp",
                instrument_frame="base")
    t_par = time.perf_counter() - t0
    cal = res.calibrated(nom)
    q_map = 1 if quick else 2
    p = plan(nom, q_map, lower=BOX_LO, upper=BOX_HI)
    meas = to_vectors(reach(p.x), FULL)
    t0 = time.perf_counter()
    plain = build_map(nom, p.x, meas, FULL)
    t_plain = time.perf_counter() - t0
    both = build_map(nom, p.x, meas, FULL, calibration=res.values("model"), calibration_source="solve")
    qt = BOX_LO + (BOX_HI - BOX_LO) * (0.05 + 0.9 * rng.uniform(0, 1, (60 if quick else 150, 6)))
    T = nom.fk(qt)
    v = to_vectors(T, FULL)

    def err(x, side=None):
        return np.linalg.norm(reach(x, side)[:, :3, 3] - T[:, :3, 3], axis=1)

    x_cal = cal.ik(T, qt, tol_pos=1e-11, tol_rot=1e-11).q
    c_plain, _ = plain.command(nom, v, FULL)
    c_both, _ = both.command(nom, v, FULL)
    random_side = rng.choice([-1.0, 1.0], size=len(qt))
    rows = [("nominal model", err(qt), "-", "-"),
            (f"parametric ({len(res.identified)} params, {n_cal} positions)", err(x_cal), n_cal, f"{t_par * 1e3:.0f}"),
            (f"map Q={q_map}", err(c_plain), len(p.x), f"{t_plain * 1e3:.0f}"),
            (f"parametric + map Q={q_map}", err(c_both), n_cal + len(p.x), "-"),
            ("parametric + map, random approach side", err(c_both, random_side), n_cal + len(p.x), "-")]
    base = rms(rows[0][1])
    print_table([{"method": m, "measured poses": n, "RMS um": um(rms(e)), "max um": um(e.max()),
                  "reduction": f"{100 * (1 - rms(e) / base):.1f}%", "fit/build ms": t} for m, e, n, t in rows])


def part_c(quick: bool, rng) -> None:
    print("\n(c) error vs number of samples, grid (multilinear) vs simplex (barycentric on Kuhn simplices), exact "
          "measurements, hexapod seed 0 and the seed's planar robot")
    rows = []
    w = World.default("hexapod", seed=0)
    for q in ((1, 2, 3) if quick else (1, 2, 3, 4)):
        for mesh in ("grid", "simplex"):
            r = parallel_case(w, "hexapod seed 0", q, mesh, rng, n_held=500)
            rows.append({k: r[k] for k in ("robot", "Q", "mesh", "samples", "after RMS um", "reduction", "build ms",
                                           "lookup us/q")})
    struts = World.from_dict({"format": "station-world/1", "units": {"length": "mm", "angle": "deg"}, "seed": 1,
                              "robot": {"model": "struts2"}, "errors": {"random": {"pivots": 0.3, "offsets": 0.3}}})
    for q in (1, 2, 4, 8, 16):
        for mesh in ("grid", "simplex"):
            r = parallel_case(struts, "struts2 (seed)", q, mesh, rng, n_held=500)
            rows.append({k: r[k] for k in ("robot", "Q", "mesh", "samples", "after RMS um", "reduction", "build ms",
                                           "lookup us/q")})
    print_table(rows)


def part_d(quick: bool, rng) -> None:
    print("\n(d) lookup cost per query vs batch size (KSF_KR only, hexapod Q=2 map, 729 nodes; 6-D multilinear "
          "reads 64 nodes, barycentric 7)")
    w = World.default("hexapod", seed=0)
    nom = w.nominal
    p = plan(nom, 2)
    meas = to_vectors(w.truth.fk(p.x, guess=nom.fk(p.x)), FULL)
    rows = []
    for mesh in ("grid", "simplex"):
        cm = build_map(nom, p.x, meas, FULL, mesh=mesh)
        for n in (1, 100, 10000, 100000):
            xq = rng.uniform(nom.lower, nom.upper, (n, 6))
            reps = max(1, 2000 // n)
            dt = min(lookup_seconds(cm, xq, 1) for _ in range(reps))
            rows.append({"mesh": mesh, "batch": n, "us/query": f"{dt * 1e6:.2f}"})
    print_table(rows)


def part_e(quick: bool, rng) -> None:
    print("\n(e) 6R arm (arm6, World.default seed 7 hidden geometry) in the correction_map procedure's work box "
          "(joints +-span around a centre),\n    map from tracker poses (noise as (a)) vs exact ones, 200 held-out "
          "configurations, errors in the robot base frame (no registration);\n    'predicted' is the plan's "
          "predicted_residual (unit pose errors, no measurement), refused by the procedure above 0.5")
    from station.solver.map.plan import predicted_residual

    good, shoulder = np.array([0.0, 0.17, 0.17, 0.0, -0.87, 0.0]), np.array([0.3, -0.9, 1.2, -0.8, 1.2, 0.4])
    cases = [("bent elbow", good, 10, 1), ("bent elbow", good, 20, 1), ("bent elbow", good, 20, 2),
             ("shoulder singularity", shoulder, 10, 1), ("shoulder singularity", shoulder, 20, 1),
             ("shoulder singularity", shoulder, 20, 2)]
    if quick:
        cases = [c for c in cases if c[3] == 1]
    worlds = [("geometry", World.default("arm6", seed=7)),
              ("geometry + compliance", World.default("arm6", seed=7, joints={
                  "compliance": {"j2": 2e-5, "j3": 3e-5, "j5": 4e-5}, "payload": 15.0}))]
    rows = []
    for wname, w in worlds:
        nom = w.nominal
        for name, centre, span, q in cases:
            lo, hi = centre - np.radians(span), centre + np.radians(span)
            p = plan(nom, q, mesh="simplex", lower=lo, upper=hi)
            x = lo + (hi - lo) * (0.1 + 0.8 * rng.uniform(0, 1, (200, 6)))
            truth = np.array([_true_tip(w, xi) for xi in x])
            reached = np.array([_true_tip(w, xi, full=True) for xi in p.x])
            e_nom = np.linalg.norm(nom.fk(x)[:, :3, 3] - truth, axis=1)
            row = {"world": wname, "box": f"{name} +-{span} deg", "Q": q, "samples": len(p.x),
                   "predicted": f"{predicted_residual(nom, p):.2f}", "nominal RMS um": um(rms(e_nom))}
            for label, noise in (("exact", False), ("tracker", True)):
                cm = build_map(nom, p.x, measure(reached, False, noise, rng), FULL, mesh="simplex")
                e = np.linalg.norm(cm.measure(nom, x)[0][:, :3] - truth, axis=1)
                row[f"map {label} um"] = um(rms(e))
            rows.append(row)
    print_table(rows)


def part_f(quick: bool, rng) -> None:
    print("\n(f) 6R arm in the correction_map procedure's box (bent elbow [0,.17,.17,0,-.87,0] rad +-10 deg, "
          "simplex) with hidden geometry (World.default seed 7),\n    gravity compliance (15 kg payload on j2, j3, "
          "j5) and backlash (0.017 deg on j1-j3), every configuration approached from below; tracker noise as (a)."
          "\n    parametric: station solve on 40 tracker positions in the box (offsets,dh,tcp; '+ compliance': the "
          "payload known, compliance identified too);\n    measuring kinematics at 200 held-out configurations "
          "vs the truth and vs one tracker reading (what the procedure judges: holdout_rms <= 0.10 mm)")
    w = World.default("arm6", seed=7, joints={"compliance": {"j2": 2e-5, "j3": 3e-5, "j5": 4e-5},
                                              "backlash": {"j1": 3e-4, "j2": 3e-4, "j3": 3e-4}, "payload": 15.0})
    nom = w.nominal
    heavy = nom.with_payload(15.0)
    centre = np.array([0.0, 0.17, 0.17, 0.0, -0.87, 0.0])
    lo, hi = centre - np.radians(10), centre + np.radians(10)
    qc = lo + (hi - lo) * rng.uniform(0, 1, (40, 6))
    pc = measure(np.array([_true_tip(w, q, full=True) for q in qc]), False, True, rng)[:, :3]
    obs = Observations(qc, np.full(len(qc), "P", dtype=object), pc)
    t0 = time.perf_counter()
    par = solve(nom, obs, "offsets,dh,tcp", instrument_frame="base")
    t_par = time.perf_counter() - t0
    parc = solve(heavy, obs, "offsets,dh,tcp,compliance", instrument_frame="base")
    x = lo + (hi - lo) * (0.1 + 0.8 * rng.uniform(0, 1, (200, 6)))
    truth = np.array([_true_tip(w, xi, full=True) for xi in x])
    seen = measure(truth, False, True, rng)[:, :3]  # one tracker reading per held-out configuration
    true_r, truth = truth[:, :3, :3], truth[:, :3, 3]

    def row(method, T, samples, t="-"):
        """``T``: predicted tool poses (N, 4, 4) or pose vectors (N, 6)."""
        if T.ndim == 2:
            T = se3.pose_to_matrix(T)
        e, e_t = np.linalg.norm(T[:, :3, 3] - truth, axis=1), np.linalg.norm(T[:, :3, 3] - seen, axis=1)
        r = np.linalg.norm(se3.orientation_error(true_r, T[:, :3, :3]), axis=1)
        return {"method": method, "measured poses": samples, "truth RMS um": um(rms(e)), "truth max um": um(e.max()),
                "truth rot RMS deg": f"{np.degrees(rms(r)):.4f}", "vs tracker RMS um": um(rms(e_t)),
                "judged": "PASS" if rms(e_t) <= 1e-4 else "FAIL", "fit/build ms": t}

    rows = [row("nominal model", nom.fk(x), "-"),
            row(f"parametric ({len(par.identified)} params)", par.calibrated(nom).fk(x), 40, f"{t_par * 1e3:.0f}"),
            row(f"parametric + compliance ({len(parc.identified)} params)", parc.calibrated(heavy).fk(x), 40)]
    for q in ((1,) if quick else (1, 2)):
        p = plan(nom, q, mesh="simplex", lower=lo, upper=hi)
        meas = measure(np.array([_true_tip(w, xi, full=True) for xi in p.x]), False, True, rng)
        for label, model, res in (("map", nom, None), ("parametric + map", nom, par),
                                  ("parametric + compliance + map", heavy, parc)):
            t0 = time.perf_counter()
            cm = build_map(model, p.x, meas, FULL, mesh="simplex", levels=p.levels,
                           calibration=None if res is None else res.values("model"))
            t = time.perf_counter() - t0
            rows.append(row(f"{label} Q={q}", cm.measure(model, x)[0], len(p.x) + (0 if res is None else 40),
                            f"{t * 1e3:.0f}"))
    print_table(rows)


def _true_tip(w: World, q, full: bool = False):
    """The world's true tool pose at encoder reading ``q`` (compliance included), approached from below."""
    w.command_q(q - 0.01)
    w.command_q(q)
    T = w.tip_pose_true()
    return T if full else T[:3, 3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer seeds, smaller grids")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--parts", default="abcdef", help="which tables to print, e.g. 'a' or 'bd'")
    a = ap.parse_args()
    for part, fn in (("a", part_a), ("b", part_b), ("c", part_c), ("d", part_d), ("e", part_e), ("f", part_f)):
        if part in a.parts:
            fn(a.quick, np.random.default_rng([a.seed, ord(part)]))


if __name__ == "__main__":
    main()
