"""UR over RTDE against the emulator process: received packages per second at 500 Hz, missed packages (target
0), and the command round trip of moveJ on a zero-length move (ur_rtde sync call: command written, script
"done", register cleared).

Run: ``.venv/bin/python bench/buses_ur.py [--seconds 60] [--moves 100]`` (or via ``bench/buses.py``)."""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import print_table  # noqa: E402 - bench/ is not a package

PERIOD = 0.002  # e-Series cycle


def stream(host: str, seconds: float) -> dict:
    """Record every package ur_rtde receives (its own file recorder) and count gaps in the controller clock."""
    import rtde_receive

    r = rtde_receive.RTDEReceiveInterface(host, 500.0, ["timestamp", "actual_q"])
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "rtde.csv"
        t0 = time.monotonic()
        r.startFileRecording(str(path), ["timestamp", "actual_q"])
        time.sleep(seconds)
        r.stopFileRecording()
        wall = time.monotonic() - t0
        r.disconnect()
        with path.open() as f:
            rows = list(csv.reader(f))
    stamps = [float(row[0]) for row in rows[1:] if row and row[0].replace(".", "", 1).isdigit()]
    gaps = [round((b - a) / PERIOD) - 1 for a, b in zip(stamps, stamps[1:], strict=False)]
    missed = sum(g for g in gaps if g > 0)
    span = stamps[-1] - stamps[0] if len(stamps) > 1 else 0.0
    return {"packages": len(stamps), "per_s": len(stamps) / wall, "missed": missed,
            "expected": round(span / PERIOD) + 1 if span else 0, "largest_gap_ms": (max(gaps) + 1) * PERIOD * 1e3
            if gaps else 0.0}


def raw_stream(host: str, seconds: float) -> dict:
    """A minimal RTDE v2 client on a plain socket that counts EVERY data package (ur_rtde's reader keeps
    only the newest of the packages it reads in one go, so its recorder undercounts bursts)."""
    import socket
    import struct

    def request(s: socket.socket, kind: str, payload: bytes = b"") -> bytes:
        s.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)
        size, _ = struct.unpack(">HB", s.recv(3, socket.MSG_WAITALL))
        return s.recv(size - 3, socket.MSG_WAITALL)

    with socket.create_connection((host, 30004), timeout=5) as s:
        request(s, "V", struct.pack(">H", 2))
        request(s, "O", struct.pack(">d", 500.0) + b"timestamp")
        request(s, "S")
        stamps: list[float] = []
        t_end = time.monotonic() + seconds
        buf = b""
        while time.monotonic() < t_end:
            buf += s.recv(65536)
            while len(buf) >= 3:
                size, kind = struct.unpack(">HB", buf[:3])
                if len(buf) < size:
                    break
                if kind == ord("U"):
                    stamps.append(struct.unpack(">d", buf[4:12])[0])
                buf = buf[size:]
    gaps = [round((b - a) / PERIOD) - 1 for a, b in zip(stamps, stamps[1:], strict=False)]
    return {"packages": len(stamps), "per_s": len(stamps) / seconds, "missed": sum(g for g in gaps if g > 0)}


def round_trips(host: str, n: int) -> list[float]:
    import rtde_control
    import rtde_receive

    r = rtde_receive.RTDEReceiveInterface(host, 500.0, ["actual_q"])
    c = rtde_control.RTDEControlInterface(host)
    try:
        q = r.getActualQ()
        c.moveJ(q, 1.0, 1.4)  # warm-up
        out = []
        for _ in range(n):
            t = time.perf_counter()
            if not c.moveJ(q, 1.0, 1.4):
                raise RuntimeError("moveJ refused by the emulator")
            out.append((time.perf_counter() - t) * 1e3)
        c.stopScript()
        return out
    finally:
        c.disconnect()
        r.disconnect()


def rows(seconds: float = 60.0, moves: int = 100) -> list[dict]:
    from station.mocks.launch import launch

    with launch("ur", model="ur5e") as emu:
        # both readers over the same minute: a raw socket counting every package, and ur_rtde's own recorder
        before = emu.dashboard("emulator stats").split()
        box: dict = {}
        t = threading.Thread(target=lambda: box.update(raw_stream(emu.host, seconds)))
        t.start()
        s = stream(emu.host, seconds)
        t.join()
        raw = box
        after = emu.dashboard("emulator stats").split()
        rt = sorted(round_trips(emu.host, moves))
    late = int(after[4]) - int(before[4])
    ticks = int(after[2]) - int(before[2])
    p95 = rt[min(len(rt) - 1, int(0.95 * len(rt)))]
    return [
        {"measurement": f"RTDE packages received, raw socket ({seconds:g} s, 500 Hz)", "value": f"{raw['per_s']:.1f}",
         "unit": "1/s", "target": "500", "note": f"{raw['packages']} packages"},
        {"measurement": "RTDE packages missed, raw socket (controller-clock gaps)", "value": str(raw["missed"]),
         "unit": "", "target": "0", "note": f"emulator cycles started late: {late}/{ticks} (max {after[6]} ms)"},
        {"measurement": f"ur_rtde RTDEReceiveInterface file recorder ({seconds:g} s)", "value": f"{s['per_s']:.1f}",
         "unit": "1/s", "target": "500",
         "note": f"{s['missed']} fewer rows than packages sent (same window as the raw socket); "
         f"largest gap {s['largest_gap_ms']:.0f} ms"},
        {"measurement": f"moveJ zero-length round trip ({moves} calls)", "value": f"{statistics.median(rt):.2f}",
         "unit": "ms median", "target": "", "note": f"p95 {p95:.2f} ms, max {rt[-1]:.2f} ms"},
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=60.0, help="how long to record the 500 Hz stream")
    ap.add_argument("--moves", type=int, default=100, help="zero-length moveJ calls to time")
    args = ap.parse_args()
    table = rows(args.seconds, args.moves)
    print_table(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
