"""The jog UI's write-back holds SIGTERM until the device is written and read back, then quits like
ctrl+q. A real signal from another process into the real app (textual, headless, on its main thread) driving
the CiA 402 emulator through canopen on a virtual bus. The write window is widened, not faked: the driver's own
``write_calibration`` runs, then waits 3 s before the read-back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from station.engine.journal import read_journal

CHILD = r"""
import asyncio, sys, time, uuid
from pathlib import Path
import numpy as np
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World
from station.robot import open_robot
from station.tui.app import JogApp
from station.tui.controller import JogController
from station.tui.session import session_header, technician_session

folder, marker = Path(sys.argv[1]), Path(sys.argv[2])
START = [0.0, -0.5, 0.5, 0.0, 0.6, 0.0]
world = World.default(model="arm6", seed=5, start=START,
                      errors={"explicit": {"offset.j2": -0.0012, "offset.j3": 0.0010, "offset.j4": 0.0015}})
chan = f"sig-{uuid.uuid4().hex[:8]}"
emu = CanopenEmulator(world, channel=chan).start()
robot = open_robot(f"canopen+virtual://{chan}?nodes=1-6&model=arm6&heartbeat_ms=250")
robot.enable()
write = type(robot).write_calibration
def slow_write(self, values):
    write(self, values)
    marker.write_text("in the window")
    time.sleep(3.0)  # signal lands here: written, not yet read back
type(robot).write_calibration = slow_write
header = session_header(identity=robot.identity(), model_name="arm6", serial="SN-S", identify="offsets",
                        reference="unknown", url="x")
ctl = JogController(robot, technician_session(robot, header, folder=folder),
                    identify="offsets")
rng = np.random.default_rng(0)
target = world.points["N"].position
while len(ctl.session.samples()) < 10:
    q0 = np.array(START) + rng.uniform(-1, 1, 6) * np.array([0.3, 0.3, 0.3, 1.3, 0.9, 1.3])
    r = world.truth.ik(target, q0, position_only=True)
    if r.ok[0] and world.truth.within_limits(r.q[0], 0.05)[0]:
        robot.move_joints(r.q[0], speed=1.0)
        ctl.record(point="N", force=True)

async def run():
    app = JogApp(ctl, poll_s=0.2)
    async with app.run_test(size=(150, 50)) as pilot:
        await pilot.press("W")
        await pilot.pause(0.2)
        await pilot.press("y")
        end = time.monotonic() + 30
        while app.is_running and time.monotonic() < end:
            await pilot.pause(0.05)
    return app

app = asyncio.run(run())
ctl.close()
robot.close()
emu.stop()
print("interrupted", app.interrupted, flush=True)
"""


@pytest.mark.timeout(120)
def test_sigterm_during_the_jog_writeback_is_held_then_quits_cleanly(tmp_path):
    folder, marker = tmp_path / "s", tmp_path / "marker"
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(folder), str(marker)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 90
        while not marker.exists():
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGTERM)
        sent = time.monotonic()
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert f"interrupted {int(signal.SIGTERM)}" in out, (out, err)  # acted on: the app quit because of it
    assert took > 2.0  # ... only after the rest of the write window (3 s pause before the read-back)
    _, events = read_journal(folder / "journal.jsonl")
    assert [e["phase"] for e in events if e["type"] == "writeback"] == ["pre-image", "written"]
    assert events[-1]["type"] == "end"  # the session was closed: verdict and end journaled
