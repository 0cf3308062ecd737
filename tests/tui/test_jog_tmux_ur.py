"""Hold-to-run on a UR in a real terminal: the real `station jog` in tmux (which reports no key release, only
the autorepeat) against the UR emulator process through ur_rtde. Keys are sent as a keyboard sends them (a
press, the repeat delay, then a repeat every ~33 ms). Ground truth: the emulated controller's joint velocities
(``actual_qd`` of the world), read by an independent RTDE client on the controller's clock.

Also: without ``--serial`` the technician confirms the serial the controller reports (Enter), and the session
is filed under it."""

from __future__ import annotations

import os
import shutil
import sys
import time

import numpy as np
import pytest
import yaml
from station.mocks.world import default_doc

from station.engine.journal import read_journal
from station.records import open_records
from station.tui.controller import HOLD_GAP_MIN_S, HOLD_RELEASE_S
from tests.tui.test_jog_tmux import Tmux

pytestmark = [pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux not installed (.ci/run installs it)"),
              pytest.mark.exclusive]  # key-repeat timing in a real terminal: run alone (make test)

START = [0.1, -1.45, 1.6, -1.72, -1.5708, 0.2]
SERIAL = "20235500011"
BRAKE_S = 0.02  # speedStop from 0.2 rad/s at the world's joint deceleration, plus one 2 ms controller cycle


def _hold(term, recv, key: str, delay: float, interval: float, seconds: float) -> dict:
    """Hold ``key``: press, ``delay``, then repeats every ``interval`` until ``seconds``. Returns the key times
    and the joint speeds the controller reported meanwhile (wall clock, controller clock)."""
    log, sent = [], []
    t0 = time.monotonic()
    next_key = t0
    first = True
    while time.monotonic() - t0 < seconds:
        now = time.monotonic()
        if now >= next_key:
            term.type_key(key)
            sent.append(time.monotonic())
            next_key = now + (delay if first else interval)
            first = False
        log.append((time.monotonic(), recv.getTimestamp(), np.abs(recv.getActualQd()).max()))
        time.sleep(0.003)
    return {"sent": np.array(sent), "log": log, "t_last_ctrl": recv.getTimestamp()}


def _standstill(recv, timeout: float = 3.0) -> tuple[float, float]:
    """(wall, controller time) when every joint speed is zero."""
    end = time.monotonic() + timeout
    while np.abs(recv.getActualQd()).max() > 1e-6:
        assert time.monotonic() < end, "the arm kept moving after the key events stopped"
        time.sleep(0.002)
    return time.monotonic(), recv.getTimestamp()


# Runs alone (exclusive): 3 of 3 at idle after the causes found were fixed (docs/jog.md). Under heavy host load
# (9-14 on 2 cores) the station or the test's key sender is starved for 0.1-2 s, which shows as stop-starts.
@pytest.mark.timeout(240)
def test_hold_to_run_on_a_ur_in_a_real_terminal(tmp_path, emulators):
    import rtde_receive

    doc = default_doc("ur5e", seed=11)
    doc["motion"].update(time_mode="sim", start=list(START))
    doc["buses"] = {"ur": {"serial": SERIAL}}
    world = tmp_path / "world.yaml"
    world.write_text(yaml.safe_dump(doc))
    emu = emulators("ur", world)
    home = tmp_path / "home"
    code = "import sys; from station.cli import main; sys.argv = ['station', *sys.argv[1:]]; main()"
    cmd = [sys.executable, "-c", code, "jog", "--robot", emu.url, "--identify", "offsets"]  # no --serial
    env = {"STATION_HOME": str(home), "TERM": "xterm-256color", "PATH": os.environ.get("PATH", ""),
           "COLUMNS": "170", "LINES": "55"}
    term = Tmux(cmd, env)
    recv = rtde_receive.RTDEReceiveInterface(emu.host)
    try:
        # the serial prompt offers what the controller reports; Enter confirms it
        term.wait_for(f"the robot reports {SERIAL}: Enter confirms it", timeout=60)
        term.keys("Enter")
        term.wait_for("live solve", timeout=60)
        term.keys("c")
        term.wait_for("enabled")
        term.keys("0")  # hold-to-run, joint mode, 10 % (25 mm/s at the tool)
        term.wait_for("hold-to-run")
        results = []
        for _ in range(3):
            h = _hold(term, recv, "q", delay=0.45, interval=0.033, seconds=1.5)
            wall, ctrl = _standstill(recv)
            results.append((h, wall - h["sent"][-1], ctrl - h["t_last_ctrl"]))
            time.sleep(0.3)
        term.keys("!")  # record here, without contact (the emulated cell's contact input is off)
        term.wait_for("recorded #1")
        term.keys("C-q")  # a sample kept: quitting asks first
        term.wait_for("Quit station jog?")
        term.keys("y")
        out = term.wait_for("EXIT=", timeout=60)
    finally:
        recv.disconnect()
        term.kill()
    for h, wall, ctrl in results:
        gaps = np.diff(h["sent"][1:])
        print(f"UR hold-to-run in tmux: {len(h['sent'])} key events, repeat every {np.median(gaps) * 1e3:.0f} ms "
              f"(p90 {np.percentile(gaps, 90) * 1e3:.0f} ms); standstill {wall * 1e3:.0f} ms (wall) / "
              f"{ctrl * 1e3:.0f} ms (controller) after the last key was sent")
    for h, wall, ctrl in results:
        log = [(t, v) for t, _, v in h["log"]]
        start = h["sent"][0]
        # the first press keeps the arm moving through the 450 ms repeat delay: once started (the first speed
        # command also arms the watchdog), no stop before the first repeat
        delay = np.array([v for t, v in log if start < t < h["sent"][1]])
        assert np.any(delay > 0.01), "the press did not start the arm before the first repeat"
        moving = delay[np.argmax(delay > 0.01):]
        assert moving.min() > 0.01, moving.min()
        # then moving while the repeats come; a repeat that tmux delivers later than 2.5 intervals (loaded
        # host: send-keys p90 up to 75 ms) is taken as a release, so allow a few short stop-starts
        during = [v for t, v in log if h["sent"][1] < t < h["sent"][-1]]
        assert np.mean(np.array(during) > 1e-4) > 0.6, np.mean(np.array(during) > 1e-4)
        # standstill after the last key event: the inferred release (2.5 repeat intervals, at most the 0.1 s
        # watchdog period) + the UI's 10 ms check + the brake; tmux/pty input latency on top (wall clock)
        assert ctrl <= HOLD_RELEASE_S + 0.01 + BRAKE_S + 0.1, ctrl
        # it waited for a gap, it did not stop between repeats: on the wall clock of the key times (the emulated
        # controller's clock falls behind wall time on a loaded host)
        assert wall >= HOLD_GAP_MIN_S - 0.02, wall
    assert "EXIT=0" in out, out
    (folder,) = list((home / "sessions").iterdir())
    header, _ = read_journal(folder / "journal.jsonl")
    assert header["serial"] == SERIAL and folder.name.startswith(f"jog-{SERIAL}-")
    records = open_records(f"sqlite:///{home / 'station.db'}")
    try:
        assert [r["session"] for r in records.sessions(SERIAL)] == [folder.name]
    finally:
        records.close()
