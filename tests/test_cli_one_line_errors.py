"""Bad input and bus faults reach the user as exactly one line and exit 2 (no library narration)."""

import subprocess
import sys
from pathlib import Path

STATION = str(Path(sys.executable).with_name("station"))
ABSENT_ARM = "canopen+virtual://nobody-here?nodes=1-6&model=arm6"  # a bus with no drive on it


def _run(*args, env=None):
    p = subprocess.run([STATION, *args], capture_output=True, text=True, timeout=60, env=env)
    return p.returncode, p.stderr.strip().splitlines()


def test_missing_cell_file_fails_before_the_robot_is_opened(tmp_path):
    rc, lines = _run("run", "zero_offsets", "--robot", ABSENT_ARM, "--serial", "S1",
                     "--cell", str(tmp_path / "absent.yaml"))
    assert rc == 2
    assert len(lines) == 1 and "cell file" in lines[0] and "absent.yaml" in lines[0], lines


def test_silent_bus_is_one_line_without_library_logging(tmp_path):
    cell = tmp_path / "cell.yaml"
    cell.write_text("format: station-cell/1\nunits: {length: mm}\npoints:\n"
                    "  A: {kind: socket, position: [350, 0, 750], approach: [0, 0, 1]}\n")
    import os

    env = {k: v for k, v in os.environ.items() if k != "STATION_DEBUG"} | {"STATION_HOME": str(tmp_path / "h")}
    rc, lines = _run("run", "zero_offsets", "--robot", ABSENT_ARM, "--serial", "S1", "--cell", str(cell), env=env)
    assert rc == 2
    assert len(lines) == 1 and lines[0].startswith("station: error:") and "does not answer" in lines[0], lines
