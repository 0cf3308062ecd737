"""Dynamixel bus cost per joint snapshot: bytes on the wire and transactions vs the protocol minimum,
and the snapshot rate through the real SDK against the emulator with wire timing at 1 Mbaud.

Run: ``.venv/bin/python bench/buses_dynamixel.py [--seconds 0.5]``. Bytes are counted at the emulator
(instruction in + status out, 4-byte Present Position per joint). ``wire_us`` = bytes x 10 bit / baud +
return delays; ``wire_hz`` its inverse (the ceiling on a real bus); ``measured_hz`` = snapshots per second
of this host through the SDK against ``station mock dynamixel --wire-timing`` (a separate process)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import dynamixel_sdk as sdk
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.launch import launch
from station.mocks.world import World

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import print_table  # noqa: E402 - bench/ is not a package

BAUD = 1_000_000


def minimum_bytes(method: str, n: int, size: int = 4) -> int:
    """Protocol 2.0 bytes per snapshot of ``n`` joints, ``size`` data bytes each (no stuffing)."""
    if method == "fast_sync_read":  # 14 + n request; 8 + n x (ERR ID DATA CRC) in one status packet
        return 14 + n + 8 + n * (size + 4)
    if method == "sync_read":  # 14 + n request; n status packets of 11 + size
        return 14 + n + n * (11 + size)
    if method == "read_per_joint":  # n x (14 request + 11 + size status)
        return n * (14 + 11 + size)
    raise ValueError(method)


def _snapshot_fn(method: str, port, ph, ids: list[int]):
    """A callable doing one snapshot; returns True on success (a loaded host can miss the SDK's timeout)."""
    if method == "read_per_joint":
        def read() -> bool:
            return all(ph.read4ByteTxRx(port, i, 132)[1] == sdk.COMM_SUCCESS for i in ids)
        return read
    group = sdk.GroupSyncRead(port, ph, 132, 4)
    for i in ids:
        group.addParam(i)
    call = group.fastSyncRead if method == "fast_sync_read" else group.txRxPacket

    def snap() -> bool:
        return call() == sdk.COMM_SUCCESS
    return snap


def _rate(port_path: str, method: str, ids: list[int], seconds: float) -> tuple[float, int]:
    """(successful snapshots per second, failed snapshots)."""
    port = sdk.PortHandler(port_path)
    try:
        port.openPort()
        port.setBaudRate(BAUD)
        snap = _snapshot_fn(method, port, sdk.PacketHandler(2.0), ids)
        snap()
        ok = failed = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            if snap():
                ok += 1
            else:
                failed += 1
        return ok / (time.perf_counter() - t0), failed
    finally:
        if port.is_open:
            port.closePort()


def measure(model: str, n: int, method: str, seconds: float, return_delay: int = 0) -> dict:
    ids = list(range(1, n + 1))
    # bytes and transactions, counted by an in-process emulator
    emu = DynamixelEmulator(World.default(model=model), ids=ids, baud=BAUD, return_delay=return_delay,
                            contact_id=None)
    port = sdk.PortHandler(emu.start().path)
    try:
        port.openPort()
        port.setBaudRate(BAUD)
        snap = _snapshot_fn(method, port, sdk.PacketHandler(2.0), ids)
        snap()
        emu.reset_stats()
        count = 50
        for _ in range(count):
            if not snap():
                raise RuntimeError(f"{method}: snapshot failed against the in-process emulator")
        st = emu.stats
        per = (st["bytes_in"] + st["bytes_out"]) / count
        trans = st["packets"] / count
    finally:
        port.closePort()
        emu.stop()
    # rate, against an emulator process answering after the wire time
    # (``station mock dynamixel --wire-timing`` in its own process, so its timing does not share our GIL)
    with launch("dynamixel", process=True, model=model, extra=("--ids", f"1-{n}", "--wire-timing", "--return-delay",
                                                                str(return_delay), "--contact-id", "none")) as emu:
        hz, failed = _rate(emu.port, method, ids, seconds)
    # fast sync read: one return delay (the later devices append back-to-back); otherwise one per answer
    delays = 1 if method == "fast_sync_read" else n
    wire_s = per * 10 / BAUD + delays * return_delay * 2e-6
    return {"joints": n, "method": method, "return_delay_us": 2 * return_delay, "bytes": round(per, 1),
            "min_bytes": minimum_bytes(method, n), "transactions": round(trans, 2), "min_transactions": 1,
            "wire_us": round(wire_s * 1e6), "wire_hz": round(1 / wire_s), "measured_hz": round(hz), "timeouts": failed}


def rows(seconds: float = 0.5) -> list[dict]:
    out = []
    for model, n in (("omx", 4), ("arm6", 6)):
        for method in ("fast_sync_read", "sync_read", "read_per_joint"):
            out.append(measure(model, n, method, seconds))
    out.append(measure("arm6", 6, "fast_sync_read", seconds, return_delay=250))  # factory default 0.5 ms
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=0.5, help="measuring time per row")
    args = ap.parse_args()
    table = rows(args.seconds)
    print_table(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
