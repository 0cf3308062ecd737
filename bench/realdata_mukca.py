# ruff: noqa: E402  (BLAS thread count must be set before numpy is imported)
"""Real data: the public MUKCa recordings (tests/data/mukca, MIT; README there), side by side with the data
set's own published optimizer.

Each robot (Franka Panda x6, KUKA LBR iiwa 14, Kinova Gen3 lite x2) seated a ball on its flange in the two
sockets (50 mm apart) of a printed fixture, ~30 times per socket, at 2-9 fixture positions. For every training
position of every robot: ONE ``station solve`` on that position (the data set's URDF, ``--tip-link ball_link``,
``--identify full``, ``--distance A,B=50mm``), then ``station fk --calibration`` on every OTHER position, scored by
the held-out consistency error (docs/solver.md): per position and socket the mean distance of the predicted ball
centres from their centroid, averaged over sockets (weighted by touches) and held-out positions; then over the
training positions of the robot.

Beside it, the same split for:
* ``nominal``: the URDF as published;
* ``MUKCa``: the data set's own optimizer, reimplemented from its paper and code (arXiv:2503.12584: every
  listed joint origin's x y z roll pitch yaw free, minimise the touch-weighted variance of each socket's predicted
  ball centres + (distance between the socket means - 50 mm)^2 + 1e-4 x |origins - nominal|^2 (the ball's
  origin not regularised), started from the nominal); here minimised by scipy's least squares to convergence;
  the reimplementation is checked against the two calibrated URDFs the data set published (panda_6, panda_7,
  trained on ``front``): ``published`` column;
* the repeatability floor: the consistency a fit of each position leaves on that position's own touches (in-sample,
  every geometric parameter free): no model predicts touches more consistently than they repeat. Where backlash
  rules (the Kinova Gen3 lite) it is millimetres, and ``station solve`` says so and does not trust the fit.

Run: .venv/bin/python bench/realdata_mukca.py [--robots panda_6,kuka_14] [--quick]   (prints the table)"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np
from scipy.optimize import least_squares

from station.kinematics import load_model, se3
from station.kinematics.urdf import chain, read_urdf

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "mukca"
STATION = str(Path(sys.executable).with_name("station"))
SPACING = 0.05  # m between the sockets
URDFS = {"panda": "panda.urdf", "kuka": "iiwa14.urdf", "dinova": "gen3lite.urdf"}
ROBOTS = ["panda_1", "panda_2", "panda_3", "panda_4", "panda_6", "panda_7", "kuka_14", "dinova_1", "dinova_2"]
REGULARISER = 1e-4  # the published optimizer's default


def urdf_of(robot: str) -> Path:
    return DATA / URDFS[robot.split("_")[0]]


def positions(robot: str) -> list[str]:
    return sorted(p.name for p in (DATA / robot).iterdir() if p.is_dir())


def touches(robot: str, pos: str) -> tuple[np.ndarray, np.ndarray]:
    """Joint readings (N, n) rad and socket labels A (hole_0) / B (hole_1) of one fixture position."""
    qs, labels = [], []
    for h, lab in ((0, "A"), (1, "B")):
        q = np.loadtxt(DATA / robot / pos / f"hole_{h}.csv", delimiter=",", ndmin=2)
        qs.append(q)
        labels += [lab] * len(q)
    return np.vstack(qs), np.array(labels, dtype=object)


def consistency(P: np.ndarray, labels: np.ndarray) -> float:
    """Held-out consistency error (m): per socket the mean distance of the predicted centres from their
    centroid, averaged over the sockets weighted by their touches (the data set's own "mean absolute error")."""
    errs, w = [], []
    for lab in ("A", "B"):
        p = P[labels == lab]
        errs.append(float(np.mean(np.linalg.norm(p - p.mean(axis=0), axis=1))))
        w.append(len(p))
    return float(np.average(errs, weights=w))


def write_csv(path: Path, q: np.ndarray, labels: np.ndarray | None = None) -> Path:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([f"q{i + 1}[rad]" for i in range(q.shape[1])] + (["point"] if labels is not None else []))
    for k, r in enumerate(q):
        w.writerow([repr(float(v)) for v in r] + ([labels[k]] if labels is not None else []))
    path.write_text(buf.getvalue())
    return path


def station(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([STATION, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def station_fk(cwd: Path, urdf: Path, q: np.ndarray, cal: Path | None) -> np.ndarray:
    write_csv(cwd / "heldout.csv", q)
    p = station("fk", "--model", str(urdf), "--tip-link", "ball_link", "--joints", "heldout.csv",
                *(["--calibration", str(cal)] if cal else []), cwd=cwd)
    if p.returncode != 0:
        raise RuntimeError(p.stderr)
    rows = list(csv.reader(ln for ln in p.stdout.splitlines() if not ln.startswith("#")))[1:]
    return np.array([[float(v) for v in r[:3]] for r in rows])


# ---- the data set's own optimizer, reimplemented ---------------------------------------------------------
class Mukca:
    """Every movable joint's origin (x y z roll pitch yaw) and the ball joint's origin free; objective of
    arXiv:2503.12584 (consistency + distortion + regulariser) as least-squares residuals."""

    def __init__(self, urdf: Path):
        robot = read_urdf(urdf)
        self.ch = chain(robot, "ball_link")
        self.free = [k for k, j in enumerate(self.ch.path) if j.movable or j.name == "ball_joint"]
        self.x0 = np.concatenate([se3.matrix_to_pose(self.ch.path[k].origin, "rpy") for k in self.free])
        self.regularised = np.concatenate([np.full(6, self.ch.path[k].name != "ball_joint") for k in self.free])

    def positions(self, x: np.ndarray, q: np.ndarray) -> np.ndarray:
        origins = {k: se3.pose_to_matrix(x[6 * i: 6 * i + 6], "rpy") for i, k in enumerate(self.free)}
        T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        i = 0
        for k, j in enumerate(self.ch.path):
            T = T @ origins.get(k, j.origin)
            if j.movable:
                M = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
                if j.type == "prismatic":
                    M[:, :3, 3] = j.axis * q[:, i, None]
                else:
                    M[:, :3, :3] = se3.rotvec_to_matrix(j.axis * q[:, i, None])
                T = T @ M
                i += 1
        return T[:, :3, 3]

    def fit(self, sets: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        lam = REGULARISER * len(sets)

        def residual(x):
            out = []
            for q, lab in sets:
                P = self.positions(x, q)
                means = []
                for s in ("A", "B"):
                    p = P[lab == s]
                    means.append(p.mean(axis=0))
                    # (N_s / (N_A + N_B)) x variance of socket s = sum |p - mean|^2 / (N_A + N_B)
                    out.append(((p - means[-1]) / np.sqrt(len(P))).ravel())
                out.append(np.array([np.linalg.norm(means[0] - means[1]) - SPACING]))
            out.append(np.sqrt(lam) * (x - self.x0)[self.regularised])
            return np.concatenate(out)

        return least_squares(residual, self.x0, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12,
                             gtol=1e-12, max_nfev=200).x


def published(robot: str) -> float | None:
    """Held-out consistency of the calibrated URDF the data set published for ``robot`` (trained on front)."""
    path = DATA / "published" / robot / "panda.urdf"
    if not path.exists():
        return None
    m = load_model(path, tip_link="ball_link")
    return float(np.mean([consistency(m.position(q), lab) for q, lab in
                          (touches(robot, p) for p in positions(robot) if p != "front")]))


def floor(robot: str) -> float:
    """The repeatability floor: at each position, the consistency of the touches the station's own fit of THAT
    position leaves (all geometry free, in-sample: it overfits, so no model predicts these touches more
    consistently), averaged over the positions. Where the touches themselves scatter (backlash), no calibration
    gets below it."""
    from station.solver import Observations, solve

    m = load_model(urdf_of(robot), tip_link="ball_link")
    out = []
    for pos in positions(robot):
        q, lab = touches(robot, pos)
        res = solve(m, Observations(q, lab), "full", "unknown", distances=[("A", "B", SPACING)])
        out.append(consistency(res.calibrated(m).position(q), lab))
    return float(np.mean(out))


def run_robot(robot: str, work: Path) -> dict:
    urdf = urdf_of(robot)
    m = load_model(urdf, tip_link="ball_link")
    mk = Mukca(urdf)
    pos = positions(robot)
    rows = {"nominal": [], "station": [], "mukca": [], "trusted": [], "why": [], "time": []}
    for train in pos:
        held = [p for p in pos if p != train]
        q, lab = touches(robot, train)
        d = work / f"{robot}-{train}"
        d.mkdir()
        write_csv(d / "train.csv", q, lab)
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        station("solve", "--model", str(urdf), "--tip-link", "ball_link", "--samples", "train.csv",
                "--identify", "full", "--distance", "A,B=50mm", "--out", "cal.json", cwd=d)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # CPU time of the whole process (the machine is shared)
        rows["time"].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
        doc = json.loads((d / "cal.json").read_text())
        rows["trusted"].append(bool(doc["trusted"]))
        rows["why"].append(doc.get("failure") or "")
        x = mk.fit([(q, lab)])
        ours, base, nom = [], [], []
        for h in held:
            qh, lh = touches(robot, h)
            ours.append(consistency(station_fk(d, urdf, qh, d / "cal.json"), lh))
            base.append(consistency(mk.positions(x, qh), lh))
            nom.append(consistency(m.position(qh), lh))
        rows["station"].append(np.mean(ours))
        rows["mukca"].append(np.mean(base))
        rows["nominal"].append(np.mean(nom))
        print(f"  {robot:9s} train {train:14s} held-out mm: nominal {np.mean(nom) * 1e3:6.3f}  station "
              f"{np.mean(ours) * 1e3:6.3f} ({'trusted' if doc['trusted'] else 'NOT trusted'})  MUKCa "
              f"{np.mean(base) * 1e3:6.3f}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default=",".join(ROBOTS))
    args = ap.parse_args()
    robots = [r.strip() for r in args.robots.split(",") if r.strip()]
    t0 = time.time()
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in robots:
            out[r] = run_robot(r, Path(tmp))
    print()
    print("| robot | positions | nominal | MUKCa (reimpl.) | MUKCa published (front) | station | station vs MUKCa "
          "| trusted | repeatability floor |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r, rows in out.items():
        pub = published(r)
        nom, ours, base = (1e3 * np.mean(rows[k]) for k in ("nominal", "station", "mukca"))
        trusted = sum(rows["trusted"])
        print(f"| {r} | {len(rows['station'])} | {nom:.3f} | {base:.4f} | {'-' if pub is None else f'{pub * 1e3:.3f}'} "
              f"| {ours:.4f} | {100 * (ours / base - 1):+.1f} % | {trusted}/{len(rows['trusted'])} | "
              f"{floor(r) * 1e3:.3f} |")
    print(f"\nwhole run {time.time() - t0:.0f} s; station solve per process (CPU): median "
          f"{np.median([t for rows in out.values() for t in rows['time']]):.2f} s, max "
          f"{np.max([t for rows in out.values() for t in rows['time']]):.2f} s; load average {os.getloadavg()[0]:.1f}")
    for r, rows in out.items():
        why = {w for w in rows["why"] if w}
        if why:
            print(f"{r}: not trusted because: {sorted(why)[0]}")


if __name__ == "__main__":
    main()
