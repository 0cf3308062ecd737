"""Start-up cost of the station command, timed from outside (the "fast start" budget).

What a factory script pays per call is the whole process: interpreter, imports, the work, the exit. This bench
writes a UR5e touch data set (50 samples, offsets + TCP + one unknown point = 12 unknowns, the `bench/solver.py`
case) and times each command as a whole process (wall, and cpu = user + sys from wait4), paired run by run with
`python -c pass` so that the ratio stays meaningful on a busy machine. Bytecode is written as an install has it
(PYTHONDONTWRITEBYTECODE is dropped for the children, and a warm-up run precedes each case):

    station --help          the CLI tree alone
    station fk ...          50 rows of joint readings -> tool poses
    station solve ...       the 12 x 50 solve end to end (target: <= 0.3 s on the station PC)
    python -c pass          the interpreter's own floor, side by side
    python -c "import numpy"   the floor of any command that computes (solve, fk)

``--baseline REF`` (a git ref of this repository, e.g. ``main``) adds the same commands of that revision, run
alternately with this one (A B A B ...) so that one table holds before and after and their ratio. The baseline's
source is exported with ``git archive`` into a temporary folder and started with the same interpreter as
``python -c "from station.cli import main; main()" ARGS`` (the console script does the same).

Run: .venv/bin/python bench/startup.py [--runs 7] [--baseline main]. Prints one table; units: seconds.
"""

from __future__ import annotations

import argparse
import csv
import os
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


def paired(cmds: list[list[str]], runs: int, env: dict) -> tuple[list[list[float]], list[list[float]]]:
    """Wall and cpu (user + sys of the child, from wait4) seconds of each command, run by run. The commands run
    in turn (A B ... A B ...), so a machine whose speed drifts moves them alike and their ratios, taken run by
    run, stay meaningful."""

    def once(c: list[str]) -> tuple[float, float]:
        t0 = time.perf_counter()
        p = subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        _, _, ru = os.wait4(p.pid, 0)
        return time.perf_counter() - t0, ru.ru_utime + ru.ru_stime

    for c in cmds:
        once(c)  # warm-up: page cache, and the bytecode of every module it imports
    walls: list[list[float]] = [[] for _ in cmds]
    cpus: list[list[float]] = [[] for _ in cmds]
    for _ in range(runs):
        for i, c in enumerate(cmds):
            wall, cpu = once(c)
            walls[i].append(wall)
            cpus[i].append(cpu)
    return walls, cpus


def ratio(a: list[float], b: list[float]) -> float:
    """Median of the run-by-run ratios a/b."""
    return statistics.median(x / max(y, 1e-6) for x, y in zip(a, b, strict=True))


def export_revision(ref: str, folder: Path) -> Path:
    """The source of revision ``ref`` laid out as installed (``station.drivers`` is ``drivers/`` etc., as
    setup.py maps them): the folder to put first on ``sys.path``."""
    repo = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "-C", str(repo), "archive", ref], capture_output=True, check=True).stdout
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    for sub in ("drivers", "mocks", "procedures"):
        if (folder / sub).is_dir() and not (folder / "station" / sub).exists():
            (folder / "station" / sub).symlink_to(folder / sub, target_is_directory=True)
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--baseline", metavar="REF", help="git ref to compare with, e.g. main")
    args = ap.parse_args()
    station = [str(Path(sys.executable).with_name("station"))]
    with tempfile.TemporaryDirectory() as d:
        samples, joints = write_data(Path(d))
        out = Path(d) / "result.json"
        before = None
        if args.baseline:
            base = export_revision(args.baseline, Path(d) / "baseline")
            before = [sys.executable, "-c", f"import sys; sys.path.insert(0, {str(base)!r}); "
                                            "from station.cli import main; main()"]
        cases = [
            ("python -c pass", [sys.executable, "-c", "pass"], False),
            ('python -c "import numpy"', [sys.executable, "-c", "import numpy"], False),
            ("station --help", ["--help"], True),
            ("station fk (50 rows)", ["fk", "--model", "ur5e", "--joints", str(joints)], True),
            ("station solve 12 x 50", ["solve", "--model", "ur5e", "--samples", str(samples), "--identify",
                                       "offsets,tcp", "--tool", "0.02,-0.01,0.12", "--out", str(out)], True),
        ]
        for prefix in [station] + ([before] if before else []):
            check = subprocess.run(prefix + cases[-1][1], capture_output=True, text=True)
            if check.returncode not in (0, 1):
                sys.exit(f"bench/startup.py: {' '.join(prefix)} solve failed: {check.stderr.strip()}")
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        floor = cases[0][1]
        print(f"station start-up, whole process (medians of {args.runs} runs, commands run in turn; "
              f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start)")
        print("cpu = user + sys of the process (robust on a busy machine); wall = what a script waits")
        head = f"{'command':<26}{'cpu s':>8}{'wall s':>9}{'cpu vs python':>15}"
        if before:
            head += f"{'before: cpu s':>15}{'wall s':>9}{'after/before cpu':>18}"
        print(head)
        for label, cmd, is_station in cases:
            row = [station + cmd if is_station else cmd]
            if before and is_station:
                row.append(before + cmd)
            row.append(floor)
            walls, cpus = paired(row, args.runs, env)
            cpu, wall = statistics.median(cpus[0]), statistics.median(walls[0])
            line = f"{label:<26}{cpu:>8.3f}{wall:>9.3f}{ratio(cpus[0], cpus[-1]):>14.1f}x"
            if len(row) == 3:
                line += (f"{statistics.median(cpus[1]):>15.3f}{statistics.median(walls[1]):>9.3f}"
                         f"{ratio(cpus[0], cpus[1]):>17.2f}x")
            print(line, flush=True)
            if label.startswith("station solve"):
                verdict = "meets" if cpu <= TARGET_SOLVE_S else "MISSES"
                print(f"{'':<26}target cpu <= {TARGET_SOLVE_S} s: {verdict} (load average now "
                      f"{os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
