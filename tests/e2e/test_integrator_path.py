"""The integrator's path with an arm of one's own, run exactly as docs/world.md gives it: from
``station mock world example --model myarm.urdf`` through ``station mock world cell``, ``station mock ur --world``,
``station run dh_full ... --identify ...`` to ``station model export --calibration SESSION``, each line a
subprocess of the installed ``station`` command in a shell. The one change to the documented lines: the emulator's
loopback address (a free one instead of 127.0.0.2, so tests can run side by side; ``--exit-with-parent`` so that
no emulator outlives the test).

Ground truth is the simulated world (``World.from_file`` on the world file the docs wrote): the calibrated URDF's
tool positions must be closer to the world's true arm than the nominal URDF's, after the best rigid alignment (a
calibration from sockets at unknown positions cannot see the base frame nor joint 1's zero)."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from station.mocks.launch import free_loopback
from station.mocks.world import World
from station.mocks.world.identity import default_serial

from station.kinematics import load_model
from tests.urdf_robots import ur5e_urdf

DOCS = Path(__file__).resolve().parents[2] / "docs" / "world.md"
BIN = Path(sys.executable).parent
SEATING = 10e-6  # m per axis: the example world's noise.seating (where a compliant ball settles)


def documented_lines() -> list[str]:
    """The ``station ...`` lines of the docs' integrator-path block, as written."""
    text = DOCS.read_text()
    block = re.search(r"```sh\n# integrator path[^\n]*\n(.*?)```", text, re.S)
    assert block, "docs/world.md lost its integrator-path block"
    return [ln.strip() for ln in block.group(1).splitlines() if ln.strip().startswith("station ")]


def aligned_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance between point sets after the best rigid motion of ``a`` onto ``b`` (Kabsch)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, 1.0, d]) @ vt
    return float(np.sqrt(np.mean(np.sum(((a - ca) @ r - (b - cb)) ** 2, axis=1))))


def _shell(line: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", line], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_own_arm_from_example_world_to_calibrated_urdf(tmp_path):
    (tmp_path / "myarm.urdf").write_text(ur5e_urdf().replace('name="ur5e_urdf"', 'name="myarm"'))
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
           "STATION_HOME": str(tmp_path / "home"), "COLUMNS": "160"}
    lines = documented_lines()
    steps = [["mock", "world"], ["mock", "world"], ["mock", "ur"], ["run", "dh_full"], ["model", "export"]]
    assert [ln.split()[1:3] for ln in lines] == steps, lines
    host = free_loopback()
    found: dict[str, str] = {}
    emulator = None
    try:
        for line in lines:
            line = line.replace("127.0.0.2", host)
            for key in ("URL", "SERIAL", "SESSION"):
                if key in found:
                    line = line.replace(f"'{key}'", shlex.quote(found[key])).replace(key, found[key])
            if line.startswith("station mock ur "):
                emulator = subprocess.Popen(["bash", "-c", f"exec {line} --exit-with-parent"], cwd=tmp_path, env=env,
                                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                ready = emulator.stdout.readline()
                assert "robot URL" in ready, ready + emulator.stderr.read()
                found["URL"] = ready.rsplit("robot URL ", 1)[1].strip()
                found["SERIAL"] = re.search(r"serial (\S+)", ready).group(1)
                continue
            out = _shell(line, tmp_path, env)
            assert out.returncode == 0, (line, out.stdout[-3000:], out.stderr[-3000:])
            if line.startswith("station mock world cell"):
                assert "(4 points)" in out.stderr and "warning" not in out.stderr, out.stderr
            if line.startswith("station run "):
                assert out.stdout.rstrip().endswith("PASS"), out.stdout[-3000:]
                found["SESSION"] = re.search(r"^session:\s+(\S+)", out.stdout, re.M).group(1)
    finally:
        if emulator is not None:
            emulator.terminate()
            emulator.wait(timeout=30)

    world = World.from_file(tmp_path / "world.yaml")
    # the emulator's URL is for this arm, as printed; its serial is the world's own
    assert f"model={tmp_path / 'myarm.urdf'}" in found["URL"] and "robot_type=UR5e" in found["URL"]
    assert found["SERIAL"] == default_serial(world)
    # the example placed sockets the arm reaches: the run touched each of them from the plan's spread
    folder = tmp_path / "home" / "sessions" / found["SESSION"]
    assert (folder / "result.json").is_file() and (folder / "samples.csv").is_file()
    result = json.loads((folder / "result.json").read_text())
    assert result["format"] == "station-calibration/1" and result["trusted"]
    # the example world hides a tool error (0.5 mm sigma): the data need the tool, dh_full solved it
    assert any(n.startswith("tcp.") for n in world.errors())
    assert result["settings"]["identify"] == "offsets,dh,tcp" and result["parameters"]["tcp.y"]["identifiable"]
    # the calibrated URDF: FK closer to the world's truth than the nominal URDF's
    calibrated = load_model(str(tmp_path / "myarm-calibrated.urdf"))
    nominal = load_model(str(tmp_path / "myarm.urdf"))
    assert calibrated.n_joints == nominal.n_joints == 6
    q = np.random.default_rng(3).uniform(-2.5, 2.5, size=(200, 6))
    truth = world.truth.position(q)
    before, after = aligned_rms(nominal.position(q), truth), aligned_rms(calibrated.position(q), truth)
    assert before > 0.5e-3, before  # the world hides errors worth calibrating
    # what the sockets let the solver see: within a few seating sigmas of the truth, far below the nominal
    assert after < 5 * SEATING and after < before / 20, (before, after)
