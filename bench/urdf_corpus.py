# ruff: noqa: E402  (BLAS thread count must be set before numpy is imported)
"""Published URDFs end to end: one whole ``station solve`` process per chain, timed (target: <= 0.5 s each).

The corpus is the BSD ``example-robot-data`` package (a dev dependency: ~70 robots, humanoids, quadrupeds, hands,
arms, flying arms), Kinova's own Gen3 lite URDF (tests/data/urdf) and the MUKCa data set's URDFs. For each file
the chain to its deepest end (``--tip-link``) gets 40 samples: random joint values, the tip's position by the
file's own transforms (``UrdfChain.fk``, independent of the model the station builds) with 20 um noise, as an
instrument in the base frame would measure it (no IK: it works for a 2-joint pendulum as for a humanoid's arm);
then ``station solve --instrument-frame base --identify offsets,tcp``. Per process (import, URDF, solve, output),
median of 3 runs: the CPU time it used (user + system, what it costs on a free core) and the wall clock (which on
the shared machine includes waiting for a core: the printed load average says how loaded it was).

Run: .venv/bin/python bench/urdf_corpus.py [--all-chains] [--runs 3]"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np

from station.kinematics import ModelFileError, load_model
from station.kinematics.urdf import chain, chain_ends, read_urdf

ROOT = Path(__file__).resolve().parents[1]
STATION = str(Path(sys.executable).with_name("station"))
TARGET_S = 0.5


def corpus() -> list[Path]:
    erd = Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
    return (sorted(erd.rglob("*.urdf")) + sorted((ROOT / "tests" / "data" / "urdf").rglob("*.urdf"))
            + sorted((ROOT / "tests" / "data" / "mukca").glob("*.urdf")))


def samples(path: Path, tip: str, out: Path, rng: np.random.Generator, n: int = 40) -> int:
    robot = read_urdf(path)
    ch = chain(robot, tip)
    m = load_model(path, tip_link=tip)
    lo, hi = np.maximum(m.lower, -np.pi), np.minimum(m.upper, np.pi)
    q = lo + (hi - lo) * rng.random((n, m.n_joints))
    truth = q + np.radians(0.2) * rng.standard_normal(m.n_joints)  # the encoders' zeros are off
    xyz = np.array([ch.fk(t)[:3, 3] for t in truth]) + rng.normal(0, 20e-6, (n, 3))
    head = [f"q{i + 1}" for i in range(m.n_joints)] + ["x", "y", "z"]
    rows = [",".join(repr(float(v)) for v in (*a, *b)) for a, b in zip(q, xyz, strict=True)]
    out.write_text(",".join(head) + "\n" + "\n".join(rows) + "\n")
    return m.n_joints


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--all-chains", action="store_true", help="every chain end of every file (default: the deepest)")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    rows = []
    t_all = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for path in corpus():
            try:
                ends = chain_ends(read_urdf(path))
            except ModelFileError as e:
                print(f"{path.name:40s} refused: {str(e).split(': ', 1)[1][:80]}")
                continue
            for tip, _ in ends if args.all_chains else ends[:1]:
                n = samples(path, tip, d / "s.csv", rng)
                walls, cpus, code = [], [], None
                for _ in range(args.runs):
                    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                    t0 = time.perf_counter()
                    p = subprocess.run([STATION, "solve", "--model", str(path), "--tip-link", tip, "--samples",
                                        "s.csv", "--instrument-frame", "base", "--identify", "offsets,tcp"],
                                       capture_output=True, text=True, cwd=d, timeout=120)
                    walls.append(time.perf_counter() - t0)
                    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                    cpus.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
                    code = p.returncode
                cpu, wall = float(np.median(cpus)), float(np.median(walls))
                rows.append((path.name, tip, n, cpu, wall, code))
                print(f"{path.name:40s} {tip:32s} {n:2d} joints  cpu {cpu:.3f} s  wall {wall:.3f} s  exit {code}",
                      flush=True)
    cpu = np.array([r[3] for r in rows])
    wall = np.array([r[4] for r in rows])
    print(f"\n{len(rows)} chains: station solve process CPU median {np.median(cpu):.3f} s, max {cpu.max():.3f} s "
          f"({rows[int(cpu.argmax())][0]}), over {TARGET_S} s: {int(np.sum(cpu > TARGET_S))}; wall median "
          f"{np.median(wall):.3f} s, max {wall.max():.3f} s; exit codes {sorted({r[5] for r in rows})}; load average "
          f"{os.getloadavg()[0]:.1f}; run {time.time() - t_all:.0f} s")


if __name__ == "__main__":
    main()
