"""Pose plans against the mounting plane and keep-outs, and what the keep-out costs in conditioning.

Per demo cell (the cell `station demo --robot ur|canopen|dynamixel` writes, and the default cells of the other
built-in models): the zero_offsets plan of today's planner (``--baseline REF``: ``station/engine/plan.py`` as
of git REF, default ``main``) next to this tree's collision-aware planner. Columns: planning time; poses whose
touch or approach pose brings a link capsule below the mounting plane or within its 10 mm clearance (checked
with ``station.kinematics.collision`` and the model's link radii); the lowest point of any checked link
envelope above the plane (mm); via poses inserted; and the conditioning of the identification: D-criterion
``det(J^T J)^(1/p)`` over the parameters the solver identifies (SI, same set on both sides, ratio after/before)
and the worst predicted standard deviation of an identified joint offset (deg) for 20 um seating noise.

The predicted std comes from the solver itself: each plan's poses are seated on the TRUE socket by the world's
truth model (demo world with hidden offsets) with 20 um noise, solved with ``station.solver.solve``, and the
covariance rescaled from the fit's residual sigma to 20 um (so the number does not depend on one noise draw).

Run: ``.venv/bin/python bench/plan_keepout.py [--baseline main] [--only ur,canopen,dynamixel,scara,ur3e,ur10e]``"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from table import print_table  # noqa: E402 - bench/ is not a package

SEAT_NOISE = 20e-6
PROC = {"identify": "offsets", "n_holdout": 4, "cone_deg": 50.0, "seed": 0}  # procedures/zero_offsets.py


def _baseline(ref: str):
    src = subprocess.run(["git", "-C", str(HERE.parent), "show", f"{ref}:station/engine/plan.py"],
                         capture_output=True, text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / "plan_baseline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("plan_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["plan_baseline"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _cases(only: list[str]):
    """(name, world, station cell, model with the cell's tool, start q, plan options)."""
    from station.mocks.world import World
    from station.mocks.world.cell import DEFAULTS

    from station.cli.run_cmd import BUS_MODELS, BUS_OPTIONS, write_demo_files
    from station.engine.cell import cell_from_dict, load_cell
    from station.kinematics import load_model

    tmp = Path(tempfile.mkdtemp())
    for name in only:
        if name in BUS_MODELS:
            world_path, cell_path, _ = write_demo_files(name, tmp / name, 5, "instant")
            world, cell = World.from_file(world_path), load_cell(cell_path)
            model_name, opts = BUS_MODELS[name], {k: v for k, v in BUS_OPTIONS[name].items() if k == "cone_deg"}
            label = f"{name} demo ({model_name})"
        else:
            world = World.default(name, seed=5)
            cell = cell_from_dict(world.station_cell(), f"{name} default cell")
            model_name, opts, label = name, {}, f"{name} default cell"
        m = load_model(model_name)
        if cell.tool:
            m = m.with_params({f"tcp.{k}": v for k, v in cell.tool.items()})
        yield label, world, cell, m, np.array(DEFAULTS[model_name]["start"]), {**PROC, **opts}


def _conditioning(world, model, plan, identified=None):
    """(D-criterion, worst offset std deg, identified names) of the fit poses, from the solver."""
    from station.solver import Observations, solve
    from station.solver.simulate import noisy_q

    fit = [p for p in plan.poses if p.set == "fit"]
    q0 = np.array([p.q for p in fit])
    true_pts = np.array([world.points[p.point].position for p in fit])
    r = world.truth.ik(true_pts, q0, position_only=True, tol_pos=1e-10, max_iter=300)
    q = noisy_q(world.truth, r.q, true_pts, SEAT_NOISE, np.random.default_rng(1))
    res = solve(model, Observations(q, np.array([p.point for p in fit], dtype=object)), identify="offsets")
    names = list(res.identified)
    info = np.linalg.inv(np.asarray(res.covariance)) * res.sigma_m ** 2  # J^T J in SI
    keep = [names.index(n) for n in (identified or names) if n in names]
    sub = info[np.ix_(keep, keep)]
    d = float(np.exp(np.linalg.slogdet(sub)[1] / len(keep)))
    cov = np.asarray(res.covariance) / res.sigma_m ** 2 * SEAT_NOISE ** 2
    std = [np.degrees(np.sqrt(cov[i, i])) for i, n in enumerate(names) if n.startswith("offset.")]
    return d, max(std), names


def _row(label, which, world, model, plan, seconds, identified=None):
    from station.kinematics.collision import Checker

    ch = Checker(model, None)
    Q = np.array([p.q for p in plan.poses])
    QA = np.array([p.approach_q for p in plan.poses])
    bad = sum((a is not None) or (b is not None) for a, b in zip(ch.hits(Q), ch.hits(QA), strict=True))
    margin = min(ch.margins(Q)[:, :, 0].min(), ch.margins(QA)[:, :, 0].min()) + ch.obstacles[0].clearance
    d, worst, names = _conditioning(world, model, plan, identified)
    return {"cell": label, "planner": which, "plan s": f"{seconds:.1f}", "poses": len(plan.poses),
            "poses into plane": bad, "lowest link mm": f"{margin * 1e3:.0f}",
            "vias": sum(len(getattr(p, "via", [])) for p in plan.poses), "D-criterion": f"{d:.4g}",
            "worst offset std deg": f"{worst:.4f}"}, names, d


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--baseline", default="main", help="git ref of today's planner (default main)")
    ap.add_argument("--only", default="ur,canopen,dynamixel,scara,ur3e,ur10e")
    args = ap.parse_args()
    from station.engine import plan as current

    old = _baseline(args.baseline)
    rows = []
    for label, world, cell, m, start, opts in _cases([s.strip() for s in args.only.split(",")]):
        pts = cell.of_kind("socket")
        t = time.perf_counter()
        before = old.generate_plan(m, pts, start, **opts)
        t_before = time.perf_counter() - t
        t = time.perf_counter()
        after = current.generate_plan(m, pts, start, keep_out=cell.keep_out, **opts)
        t_after = time.perf_counter() - t
        rb, names, db = _row(label, f"{args.baseline}", world, m, before, t_before)
        ra, _, da = _row(label, "keep-out", world, m, after, t_after, names)
        ra["D after/before"] = f"{da / db:.2f}"
        rows += [rb, ra]
    print_table(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
