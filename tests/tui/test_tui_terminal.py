"""`station jog` as a technician runs it: the real command in a real (pseudo-)terminal, keys typed as bytes,
against an emulated Dynamixel arm; quitting leaves a complete session behind."""

from __future__ import annotations

import os
import select
import subprocess
import sys
import time

import numpy as np
import pytest
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.world import World

from station.engine.journal import read_journal
from station.records import open_records

START = [0.2, -0.3, 0.4, 0.1]


def _read_until(fd: int, proc: subprocess.Popen, needle: bytes, timeout: float) -> bytes:
    out = b""
    end = time.monotonic() + timeout
    while time.monotonic() < end and needle not in out:
        r, _, _ = select.select([fd], [], [], 0.1)
        if r:
            try:
                out += os.read(fd, 65536)
            except OSError:
                break
        elif proc.poll() is not None:
            break
    return out


def _drain(fd: int, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            try:
                os.read(fd, 65536)
            except OSError:
                return


@pytest.mark.timeout(90)
def test_station_jog_in_a_terminal(tmp_path):
    world = World.default(model="omx", seed=2, start=START)
    emu = DynamixelEmulator(world, ids=[11, 12, 13, 14])
    path = emu.start().path
    master, slave = os.openpty()
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home"), "TERM": "xterm-256color", "COLUMNS": "140",
           "LINES": "45"}
    code = "import sys; from station.cli import main; sys.argv = ['station', *sys.argv[1:]]; main()"
    proc = subprocess.Popen([sys.executable, "-c", code, "jog", "--robot",
                             f"dynamixel://{path}?baud=1000000&ids=11-14&contact=200&serial=OMX-7", "--model", "omx",
                             "--serial", "OMX-7", "--identify", "offsets"],
                            stdin=slave, stdout=slave, stderr=slave, env=env, start_new_session=True)
    os.close(slave)
    try:
        screen = _read_until(master, proc, b"live solve", timeout=45)
        assert b"live solve" in screen, screen[-2000:]
        q0 = world.encoder_q()
        for key in (b"c", b"3", b"w"):  # enable, 1 deg steps, J2 +
            os.write(master, key)
            _drain(master, 0.3)
        end = time.monotonic() + 15  # the keys are queued in order; a loaded machine may take a while
        while abs(world.encoder_q()[1] - q0[1]) < np.deg2rad(0.5) and time.monotonic() < end:
            _drain(master, 0.1)
        _drain(master, 0.3)
        assert world.encoder_q()[1] - q0[1] == pytest.approx(np.deg2rad(1.0), abs=2 * np.pi / 4096)
        os.write(master, b"\x11")  # ctrl+q: nothing at stake (no sample, arm still), so no question
        tail = _read_until(master, proc, b"journal stays in", timeout=20)
        assert proc.wait(timeout=20) == 0, tail[-2000:]
        tail += _read_until(master, proc, b"\n", 2)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        os.close(master)
        emu.stop()
    sessions = list((tmp_path / "home" / "sessions").iterdir())
    assert len(sessions) == 1 and sessions[0].name.startswith("jog-OMX-7-")
    header, events = read_journal(sessions[0] / "journal.jsonl")
    assert header["serial"] == "OMX-7" and header["model"] == "omx" and header["procedure"] == "jog"
    assert events[-1]["type"] == "end"
    assert (sessions[0] / "samples.csv").read_text().splitlines()[1].startswith("q1[rad],q2[rad]")
    assert not world.is_moving()
    # no sample kept: nothing is filed under the robot's serial (the journal stays in the folder), and the exit
    # lines say only that: no "session saved", no verdict, no solve line for an empty samples file
    after_ui = tail.decode(errors="replace").rpartition("\x1b[?1049l")[2]  # what is printed after the UI closed
    text = after_ui.replace("\r", "").replace("\n", "")
    assert "no samples kept: the session is not stored" in text and sessions[0].name in text
    assert "session saved" not in text and "verdict" not in text and "station solve" not in text
    records = open_records(f"sqlite:///{tmp_path / 'home' / 'station.db'}")
    try:
        stored = records.sessions("OMX-7")
    finally:
        records.close()
    assert stored == []
