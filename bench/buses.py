"""Bus benchmark tables, one per bus, from each bus's own bench module (bench/buses_<bus>.py).

Run: ``.venv/bin/python bench/buses.py [--only dynamixel,canopen,ur] [--ur-seconds 60]``"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from table import print_table  # noqa: E402 - bench/ is not a package


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", HERE / f"buses_{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--only", default="dynamixel,canopen,ur")
    ap.add_argument("--ur-seconds", type=float, default=60.0)
    args = ap.parse_args()
    for i, bus in enumerate(b.strip() for b in args.only.split(",")):
        module = _load(bus)
        kw = {"seconds": args.ur_seconds} if bus == "ur" else {}
        print(("\n" if i else "") + f"## {bus}")
        print_table(module.rows(**kw))  # each bus has its own columns: one table per bus
    return 0


if __name__ == "__main__":
    sys.exit(main())
