# ruff: noqa: E402  (BLAS thread count must be set before numpy is imported)
"""The real-data benchmark, simulated (docs/solver.md, real data): train on ONE fixture position, predict the others.

For each of several simulated 7-DOF arms (``station.mocks.world.realdata``: hidden geometry errors and joint
compliance, a ball tool 30 mm beyond a rotated hand, two sockets 50 mm apart, ~30 seated touches per socket,
0.05-0.1 mm seating noise, several fixture positions):

  station solve --model arm7.urdf --tip-link ball --samples train.csv --identify full,compliance \\
                --distance A,B=50mm --out cal.json                         (fixture position 1 only)
  station fk --model arm7.urdf --tip-link ball --calibration cal.json --joints heldout.csv

and the held-out consistency error (docs/solver.md, "Held-out consistency error"): per held-out fixture
position and socket, the mean distance of the predicted ball centres from their centroid; averaged over
sockets and held-out positions per robot, then over the robots. Beside it: the nominal model and the
geometry-only fit (``--identify full``), and the published best result on real data of this kind (0.298 mm).

Run: .venv/bin/python bench/realdata.py [--robots 5] [--positions 4] [--per-socket 30]"""

from __future__ import annotations

import argparse
import csv
import io
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the test URDFs (tests/urdf_robots.py)

import urdf_robots
from station.mocks.world.realdata import SOCKET_SPACING, arm_world, consistency, two_socket_data

PUBLISHED_MM = 0.298  # best published mean held-out consistency error on real 7-DOF two-socket data
STATION = str(Path(sys.executable).with_name("station"))


def write_csv(path: Path, q: np.ndarray, point: np.ndarray | None = None) -> Path:
    head = [f"q{i + 1}[rad]" for i in range(q.shape[1])] + (["point"] if point is not None else [])
    rows = [[repr(float(v)) for v in r] + ([str(p)] if point is not None else [])
            for r, p in zip(q, point if point is not None else [None] * len(q), strict=True)]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)
    w.writerows(rows)
    path.write_text(buf.getvalue())
    return path


def station(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([STATION, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def predict(urdf: Path, joints: Path, cal: Path | None, cwd: Path) -> np.ndarray:
    args = ["fk", "--model", str(urdf), "--tip-link", "ball", "--joints", str(joints)]
    if cal is not None:
        args += ["--calibration", str(cal)]
    p = station(*args, cwd=cwd)
    if p.returncode != 0:
        raise RuntimeError(p.stderr.strip())
    rows = [r for r in csv.reader(ln for ln in p.stdout.splitlines() if not ln.startswith("#"))][1:]
    return np.array([[float(v) for v in r[:3]] for r in rows])


def held_out_error(P: np.ndarray, data, mask: np.ndarray) -> float:
    """Mean over the held-out fixture positions of the consistency error (m)."""
    fx, pt = data.fixture[mask], data.point[mask]
    return float(np.mean([consistency(P[fx == f], pt[fx == f]) for f in dict.fromkeys(fx.tolist())]))


def run_robot(seed: int, urdf: Path, work: Path, positions: int, per_socket: int) -> dict:
    world = arm_world(str(urdf), seed)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 23]))
    noise = float(rng.uniform(0.05e-3, 0.1e-3))
    t0 = time.perf_counter()
    data = two_socket_data(world, rng, positions, per_socket, noise)
    t_data = time.perf_counter() - t0
    train, held = data.where("1"), ~data.where("1")
    d = work / f"robot{seed}"
    d.mkdir()
    write_csv(d / "train.csv", data.q[train], data.point[train])
    write_csv(d / "heldout.csv", data.q[held])
    out = {"seed": seed, "noise_mm": noise * 1e3, "data_s": t_data, "n_train": int(train.sum()),
           "n_heldout": int(held.sum())}
    out["nominal"] = held_out_error(predict(urdf, d / "heldout.csv", None, d), data, held)
    for ident in ("full", "full,compliance"):
        cal = d / f"cal_{ident.replace(',', '_')}.json"
        t0 = time.perf_counter()
        p = station("solve", "--model", str(urdf), "--tip-link", "ball", "--samples", "train.csv", "--identify",
                    ident, "--distance", f"A,B={SOCKET_SPACING * 1e3:g}mm", "--out", cal.name, cwd=d)
        out[f"{ident}_s"] = time.perf_counter() - t0
        out[f"{ident}_trusted"] = p.returncode == 0
        if not cal.exists():
            raise RuntimeError(f"robot {seed} {ident}: {p.stderr.strip()}")
        out[ident] = held_out_error(predict(urdf, d / "heldout.csv", cal, d), data, held)
    # the floor: the seating noise alone (the truth's own predictions of the held-out touches)
    theta = np.array([world.gravity.deflect(q) for q in data.q[held]])
    out["truth"] = held_out_error(world.truth.position(theta), data, held)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--positions", type=int, default=4, help="fixture positions per robot (1 train, rest held out)")
    ap.add_argument("--per-socket", type=int, default=30)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        urdf = work / "arm7.urdf"
        urdf.write_text(urdf_robots.arm7_urdf())
        rows = [run_robot(s + 1, urdf, work, a.positions, a.per_socket) for s in range(a.robots)]
    print(f"held-out consistency error (mm): train on fixture position 1 ({a.per_socket} touches per socket), "
          f"predict positions 2..{a.positions} with station fk --calibration")
    print(f"{'robot':>5} {'noise':>6} {'nominal':>8} {'full':>8} {'full,compl':>10} {'truth':>7} "
          f"{'trusted':>8} {'solve s':>8}")
    for r in rows:
        print(f"{r['seed']:>5} {r['noise_mm']:>6.3f} {r['nominal'] * 1e3:>8.4f} {r['full'] * 1e3:>8.4f} "
              f"{r['full,compliance'] * 1e3:>10.4f} {r['truth'] * 1e3:>7.4f} "
              f"{'yes' if r['full,compliance_trusted'] else 'NO':>8} {r['full,compliance_s']:>8.2f}")
    m = {k: float(np.mean([r[k] for r in rows])) * 1e3 for k in ("nominal", "full", "full,compliance", "truth")}
    print(f"{'mean':>5} {'':>6} {m['nominal']:>8.4f} {m['full']:>8.4f} {m['full,compliance']:>10.4f} "
          f"{m['truth']:>7.4f}")
    print(f"published best (real data): {PUBLISHED_MM:.3f} mm; ours (full,compliance): {m['full,compliance']:.4f} mm "
          f"= {m['full,compliance'] / PUBLISHED_MM:.2f} x published; nominal {m['nominal']:.4f} mm; "
          f"seating-noise floor {m['truth']:.4f} mm")


if __name__ == "__main__":
    main()
