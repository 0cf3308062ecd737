"""End-of-line benchmark: the ``zero_offsets`` procedure on each emulated bus in real-time motion mode.

Per bus: total time of ``station run`` (connect to report), the pure motion time of the emulated robot (the
world's joints moving, sampled every 0.5 ms), the station's overhead (everything else) as a fraction of
motion time (target <= 5 % for the sampling loop), and samples per minute. The overhead is split into the
sampling loop (connect .. last sample: bus traffic, seating, journal fsyncs, planning) and the tail (solve,
records database, HTML report with plots).

The Dynamixel and CANopen emulators run in this process (threads) so the world's motion can be observed; the
UR emulator is a separate process (``station mock ur``) whose motion is observed over a second RTDE client.
The station talks to each over the real wire (pty, python-can virtual bus, loopback TCP with ur_rtde).

Run: ``.venv/bin/python bench/eol.py [--only ur,canopen,dynamixel] [--poses 20] [--time-scale 1]
[--canopen-sync-ms 10] [--calls]``; ``--calls`` also prints, per robot method, the calls and the time spent
inside them while nothing moves (where the driver+bus share goes)."""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import yaml


class MotionMeter:
    """Integrates the time the robot's joints are moving: ``is_moving()`` polled every ``period`` s."""

    def __init__(self, is_moving, period: float = 0.0005) -> None:
        self.is_moving, self.period = is_moving, period
        self.moving = 0.0
        self.samples: list[tuple[float, float]] = []  # (wall time.time(), seconds of motion ending then)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        last = time.perf_counter()
        was = False
        while not self._stop.is_set():
            now = time.perf_counter()
            if was:
                self.moving += now - last
                self.samples.append((time.time(), now - last))
            was = self.is_moving()
            last = now
            time.sleep(self.period)

    def until(self, t: float) -> float:
        return sum(dt for when, dt in self.samples if when <= t)

    def __enter__(self) -> MotionMeter:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


class TimedRobot:
    """Forwards to a Robot and adds up the wall time spent inside its calls (driver + bus + waiting for motion)."""

    def __init__(self, robot) -> None:
        self._robot = robot
        self.calls: list[tuple[float, float]] = []  # wall-clock (start, end) of every call
        self.named: list[tuple[str, float, float]] = []  # (method, start, end)

    def __getattr__(self, name):
        attr = getattr(self._robot, name)
        if not callable(attr):
            return attr

        def timed(*a, **kw):
            t = time.time()
            try:
                return attr(*a, **kw)
            finally:
                t_end = time.time()
                self.calls.append((t, t_end))
                self.named.append((name, t, t_end))

        return timed

    def until(self, t: float) -> float:
        return sum(min(b, t) - a for a, b in self.calls if a < t)

    def breakdown(self, meter: MotionMeter, t_end: float) -> list[tuple[str, int, float, float]]:
        """Per robot method up to ``t_end``: (name, calls, seconds inside, seconds inside while not moving)."""
        import bisect

        when = [w for w, _ in meter.samples]
        cum = [0.0]
        for _, dt in meter.samples:
            cum.append(cum[-1] + dt)
        out: dict[str, list] = {}
        for name, a, b in self.named:
            if a >= t_end:
                continue
            b = min(b, t_end)
            moving = cum[bisect.bisect_right(when, b)] - cum[bisect.bisect_right(when, a)]
            row = out.setdefault(name, [0, 0.0, 0.0])
            row[0] += 1
            row[1] += b - a
            row[2] += max(0.0, (b - a) - moving)
        return sorted(((k, *v) for k, v in out.items()), key=lambda r: -r[3])


def _ur_motion(url: str):
    """The UR emulator is a separate process (ur_rtde's blocking calls hold the GIL, an in-process server would
    starve): motion is observed as the controller reports it, joint velocities over a second RTDE client."""
    import rtde_receive

    host = url.split("://", 1)[1].split("?", 1)[0]
    r = rtde_receive.RTDEReceiveInterface(host, -1.0, ["timestamp", "actual_qd"])
    return (lambda: max(abs(v) for v in r.getActualQd()) > 1e-5), r.disconnect


def run_bus(bus: str, folder: Path, poses: int, time_scale: float, seed: int = 7,
            sync_ms: float | None = None, calls: bool = False) -> dict:
    from station.mocks.world import World

    from station.api import run as start
    from station.cli.run_cmd import BUS_OPTIONS, demo_world
    from station.engine import read_journal

    doc = demo_world(bus, seed, "realtime")
    doc["motion"]["time_scale"] = time_scale
    serial = doc["buses"]["ur"]["serial"] if bus == "ur" else f"BENCH-{bus.upper()}"
    world_path, cell_path = folder / f"{bus}-world.yaml", folder / f"{bus}-cell.yaml"
    world_path.write_text(yaml.safe_dump(doc))
    world = World.from_file(world_path)
    cell_path.write_text(yaml.safe_dump(world.station_cell()))
    from station.mocks.launch import launch

    # UR: a child process serving the world file; the others in this process, serving ``world`` itself
    emu = launch(bus, world_path if bus == "ur" else world, serial=None if bus == "ur" else serial).start()
    url, stop = emu.url + ("" if sync_ms is None else f"&sync_ms={sync_ms:g}"), emu.close
    if bus == "ur":
        is_moving, close_meter = _ur_motion(url)
    else:
        is_moving, close_meter = world.is_moving, (lambda: None)
    from station.robot import open_robot

    try:
        with MotionMeter(is_moving, 0.005) as meter:
            t0 = time.time()
            robot = TimedRobot(open_robot(url))
            out = start("zero_offsets", url, serial, cell=cell_path, db=f"sqlite:///{folder / 'records.db'}",
                        options={**BUS_OPTIONS[bus], "n_fit": poses, "n_holdout": 4}, robot=robot)
            t1 = time.time()
    finally:
        close_meter()
        stop()
    if out.status != "completed":
        raise SystemExit(f"{bus}: {out.status}: {out.error}")
    _, events = read_journal(out.folder / "journal.jsonl")
    samples = [e for e in events if e.type == "sample"]
    t_last = samples[-1].t  # when the last sample was journaled
    total = t1 - t0
    motion = meter.until(t_last)  # up to the last sample: the last retreat belongs to the tail
    loop_over = (t_last - t0) - motion
    # the engine's own share (planning, IK, journal fsyncs): loop time outside robot calls
    engine = (t_last - t0) - robot.until(t_last)
    if calls:
        print(f"# {bus}: robot calls up to the last sample (s inside / s inside while nothing moves)")
        for name, n, inside, still in robot.breakdown(meter, t_last):
            print(f"#   {name:16s} {n:5d} calls  {inside:7.2f} s  {still:6.2f} s not moving  "
                  f"({1e3 * still / n:6.1f} ms/call)")
    return {
        "bus": bus + ("" if sync_ms is None else f" (sync {sync_ms:g} ms)"), "model": world.nominal.name,
        "samples": len(samples), "verdict": "PASS" if out.passed else "FAIL",
        "total_s": f"{total:.1f}", "motion_s": f"{motion:.1f}", "loop_s": f"{t_last - t0:.1f}",
        "loop_overhead": f"{100 * loop_over / motion:.1f} %",
        "engine": f"{100 * engine / motion:.1f} %",
        "driver+bus": f"{100 * (loop_over - engine) / motion:.1f} %",
        "tail_s (solve+db+report)": f"{t1 - t_last:.2f}",
        "total_overhead": f"{100 * (total - meter.moving) / meter.moving:.1f} %",
        "samples/min": f"{60 * len(samples) / total:.1f}",
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="ur,canopen,dynamixel")
    ap.add_argument("--poses", type=int, default=20, help="fit poses (4 held-out poses are added)")
    ap.add_argument("--time-scale", type=float, default=1.0, help="world seconds per wall second (1 = real time)")
    ap.add_argument("--canopen-sync-ms", type=float, default=None,
                    help="also run CANopen with this SYNC period (URL sync_ms; the driver's default is 4 ms)")
    ap.add_argument("--calls", action="store_true",
                    help="print each robot method's calls and its time inside while nothing moves")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["STATION_HOME"] = tmp
        for bus in [b.strip() for b in args.only.split(",") if b.strip()]:
            rows.append(run_bus(bus, Path(tmp), args.poses, args.time_scale, calls=args.calls))
            print(f"# {bus} done", flush=True)
            if bus == "canopen" and args.canopen_sync_ms:
                rows.append(run_bus(bus, Path(tmp), args.poses, args.time_scale, sync_ms=args.canopen_sync_ms,
                                    calls=args.calls))
    cols = list(rows[0])
    widths = {c: max(len(c), *(len(str(r[c])) for r in rows)) for c in cols}
    print(" | ".join(c.ljust(widths[c]) for c in cols))
    print("-|-".join("-" * widths[c] for c in cols))
    for r in rows:
        print(" | ".join(str(r[c]).ljust(widths[c]) for c in cols))
    print("loop_overhead = (connect .. last sample) - motion, as a fraction of motion (target <= 5 %), split into "
          "engine (outside robot calls: plan, IK, journal) and driver+bus (inside robot calls, not moving); "
          "total_overhead adds the last retreat, solve, records and the HTML report.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
