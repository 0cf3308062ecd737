"""Start-up cost of the station command, timed from outside (issue 8, "fast start").

What a factory script pays per call is the whole process: interpreter, imports, the work, the exit. This bench
writes a UR5e touch data set (50 samples, offsets + TCP + one unknown point = 12 unknowns, the `bench/solver.py`
case) and times, with `farm-bench` (whole-process wall/cpu, medians of paired runs) when it is installed, else
with a plain subprocess loop:

    station --help          the CLI tree alone
    station fk ...          50 rows of joint readings -> tool poses
    station solve ...       the 12 x 50 solve end to end (target: <= 0.3 s on the station PC)
    python -c pass          the interpreter's own floor, side by side

Run: .venv/bin/python bench/startup.py [--runs 7]. Prints one table; units: seconds.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from station.kinematics import load_model
from station.solver.simulate import noisy_q, touch_q

UR_HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
SIGMA = 20e-6  # m, touch noise at the tool
TARGET_SOLVE_S = 0.3


def write_data(folder: Path, n: int = 50, seed: int = 1) -> tuple[Path, Path]:
    """A touch data set on a UR5e with hidden offset/TCP errors: samples.csv (q in rad, one point) and q.csv."""
    rng = np.random.default_rng(seed)
    nominal = load_model("ur5e").with_params({"tcp.x": 0.02, "tcp.y": -0.01, "tcp.z": 0.12})
    names = [x for x in nominal.select("offsets,tcp") if x not in ("offset.j1", "offset.j6")]
    truth = nominal.with_params({x: nominal.param(x) + rng.normal(0, 1e-3) for x in names})
    c = truth.position(UR_HOME)
    q = touch_q(truth, c, n, rng, centre=UR_HOME, spread=0.35)
    q = noisy_q(truth, q, np.broadcast_to(c, q.shape[:1] + (3,)), SIGMA, rng)
    samples, joints = folder / "samples.csv", folder / "q.csv"
    with open(samples, "w", newline="") as fh:
        fh.write("# bench/startup.py: UR5e touches of one point; joints in rad\n")
        w = csv.writer(fh)
        w.writerow([f"q{i + 1}[rad]" for i in range(6)] + ["point"])
        for row in q:
            w.writerow([repr(float(v)) for v in row] + ["A"])
    with open(joints, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([f"q{i + 1}[rad]" for i in range(6)])
        for row in q:
            w.writerow([repr(float(v)) for v in row])
    return samples, joints


def farm_bench(cmd: list[str], runs: int) -> tuple[float, float] | None:
    """Median (wall, cpu) seconds of ``cmd`` measured by farm-bench, or None when it is not installed."""
    fb = shutil.which("farm-bench")
    if fb is None:
        return None
    out = subprocess.run([fb, "-n", str(runs), "--timeout", "300", "--", *cmd], capture_output=True, text=True)
    text = out.stdout + out.stderr
    wall = re.search(r"A wall s\s+([0-9.]+)\s+([0-9.]+)", text)
    cpu = re.search(r"A cpu s\s+([0-9.]+)\s+([0-9.]+)", text)
    return (float(wall.group(2)), float(cpu.group(2))) if wall and cpu else None


def loop(cmd: list[str], runs: int) -> tuple[float, float]:
    """Fallback: median wall and cpu (children's user + sys) seconds from a plain subprocess loop."""
    walls, cpus = [], []
    for _ in range(runs + 1):
        c0 = os.times()
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        walls.append(time.perf_counter() - t0)
        c1 = os.times()
        cpus.append(c1.children_user - c0.children_user + c1.children_system - c0.children_system)
    return statistics.median(walls[1:]), statistics.median(cpus[1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    station = str(Path(sys.executable).with_name("station"))
    with tempfile.TemporaryDirectory() as d:
        samples, joints = write_data(Path(d))
        out = Path(d) / "result.json"
        cases = [
            ("python -c pass", [sys.executable, "-c", "pass"]),
            ("station --help", [station, "--help"]),
            ("station fk (50 rows)", [station, "fk", "--model", "ur5e", "--joints", str(joints)]),
            ("station solve 12 x 50", [station, "solve", "--model", "ur5e", "--samples", str(samples),
                                       "--identify", "offsets,tcp", "--tool", "0.02,-0.01,0.12",
                                       "--out", str(out)]),
        ]
        check = subprocess.run(cases[-1][1], capture_output=True, text=True)
        if check.returncode not in (0, 1):
            sys.exit(f"bench/startup.py: station solve failed: {check.stderr.strip()}")
        env_note = "farm-bench medians" if shutil.which("farm-bench") else "subprocess loop medians"
        print(f"station start-up, whole process ({env_note}, {args.runs} runs; {os.cpu_count()} cores)")
        print("cpu = user + sys of the process (robust on a busy machine); wall = what a script waits")
        print(f"{'command':<26}{'cpu s':>8}{'wall s':>9}{'cpu vs python':>15}")
        floor = None
        for label, cmd in cases:
            wall, cpu = farm_bench(cmd, args.runs) or loop(cmd, args.runs)
            floor = floor or cpu
            print(f"{label:<26}{cpu:>8.3f}{wall:>9.3f}{cpu / floor:>14.1f}x")
            if label.startswith("station solve"):
                verdict = "meets" if cpu <= TARGET_SOLVE_S else "MISSES"
                print(f"{'':<26}target cpu <= {TARGET_SOLVE_S} s: {verdict}")


if __name__ == "__main__":
    main()
