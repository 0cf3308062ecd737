"""CANopen CiA 402 benchmark: frames per joint snapshot, SDOs per cycle (target 0), achievable snapshot rate.

The station driver (``CanopenRobot``) reads an emulated 6-drive arm6 through real python-can + canopen,
in-process on the ``virtual`` interface and through the socketcand hub over TCP loopback. A sniffer on
the drives' side of the wire counts every frame. Bus load is what the counted frames would occupy on a
1 Mbit/s CAN bus (47 + 8*DLC bits per standard frame, +20 % bit stuffing).

Run: ``.venv/bin/python bench/buses_canopen.py [--snapshots 200]``"""

from __future__ import annotations

import argparse
import sys
import time
import uuid
from pathlib import Path

import can
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.canopen.hub import SocketcandHub
from station.mocks.world import World

from station.robot import open_robot

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import print_table  # noqa: E402 - bench/ is not a package

N_NODES = 6


def _frame_bits(m: can.Message) -> float:
    return (47 + 8 * m.dlc) * 1.2


def measure(transport: str, sync_ms: float, snapshots: int = 200) -> dict:
    chan = f"bench-{uuid.uuid4().hex[:8]}"
    world = World.default(model="arm6", seed=1)
    emu = CanopenEmulator(world, channel=chan).start()
    hub = None
    try:
        if transport == "socketcand":
            hub = SocketcandHub(chan, port=0).start()
            url = f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6&sync_ms={sync_ms}"
        else:
            url = f"canopen+virtual://{chan}?nodes=1-6&model=arm6&sync_ms={sync_ms}"
        robot = open_robot(url)
        sniff = can.Bus(interface="virtual", channel=chan)
        try:
            for _ in range(5):
                robot.joint_positions()
            while sniff.recv(0) is not None:
                pass
            t0 = time.perf_counter()
            latencies = []
            for _ in range(snapshots):
                t = time.perf_counter()
                robot.joint_positions()
                latencies.append(time.perf_counter() - t)
            elapsed = time.perf_counter() - t0
            frames = []
            while (m := sniff.recv(0)) is not None:
                frames.append(m)
        finally:
            sniff.shutdown()
            robot.close()
    finally:
        if hub is not None:
            hub.stop()
        emu.stop()
    syncs = sum(m.arbitration_id == 0x80 for m in frames)
    sdo = sum(0x580 <= m.arbitration_id < 0x680 for m in frames)
    tpdo1 = sum(0x181 <= m.arbitration_id <= 0x180 + N_NODES for m in frames)
    latencies.sort()
    return {
        "transport": transport,
        "sync_ms": sync_ms,
        "snapshots": snapshots,
        "frames/snapshot": round(len(frames) / snapshots, 2),
        "min frames": 1 + N_NODES,  # one SYNC + one TPDO per drive
        "TPDO1/SYNC": round(tpdo1 / max(syncs, 1), 2),
        "SDO/cycle": round(sdo / max(syncs, 1), 3),
        "snapshot Hz": round(snapshots / elapsed, 1),
        "latency ms (median)": round(1e3 * latencies[len(latencies) // 2], 2),
        "latency ms (p95)": round(1e3 * latencies[int(0.95 * (len(latencies) - 1))], 2),
        "bus load % @1M": round(100 * sum(_frame_bits(m) for m in frames) / elapsed / 1e6, 1),
    }


def rows(snapshots: int = 200) -> list[dict]:
    out = []
    for transport in ("virtual", "socketcand"):
        for sync_ms in (10.0, 2.0, 1.0):
            out.append(measure(transport, sync_ms, snapshots))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--snapshots", type=int, default=200)
    args = ap.parse_args()
    table = rows(args.snapshots)
    print_table(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
