"""correction_map after a crash of the tracker: the emulator PROCESS (``station mock tracker --canopen``: the world's
CiA 402 drives behind socketcand and the tracker) is killed mid-run and comes back with the tracker on another
port; ``station resume SESSION --tracker NEW_URL`` continues on the new address (journaled), and an instrument
with another serial there is refused in one line, exit 2, before anything moves."""

import json
import os
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
import yaml

from station.api import run as start
from station.engine import read_journal

SERIAL = "HX-0077"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Emulator:
    """``station mock tracker --world W --canopen --can-port P`` as a real process: its tracker URL and robot URL."""

    def __init__(self, world, can_port: int) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "station.cli", "mock", "tracker", "--world", str(world),
                                      "--canopen", "--can-port", str(can_port)], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.tracker = self.proc.stdout.readline().split()[3]
        # a slower SYNC and a longer heartbeat consumer time (driver URL options): the CI machine is shared
        self.robot = self.proc.stdout.readline().split()[5] + "&sync_ms=20&heartbeat_timeout_ms=5000"

    def kill(self) -> None:  # a crash: no teardown of its sockets
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)
        self.proc.stdout.close()
        self.proc.stderr.close()


@pytest.fixture
def worlds(tmp_path):
    doc = yaml.safe_load(subprocess.run([sys.executable, "-m", "station.cli", "mock", "world", "example", "--model",
                                         "hexapod"], capture_output=True, text=True, check=True).stdout)
    doc.setdefault("buses", {})["tracker"] = {"serial": "LT-EMU-0001"}
    same = tmp_path / "world.yaml"
    same.write_text(yaml.safe_dump(doc))
    doc["buses"]["tracker"]["serial"] = "LT-OTHER-0002"  # another instrument, same place, same world
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(doc))
    return same, other


def _resume(tmp_path, session, url):
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    return subprocess.run([sys.executable, "-m", "station.cli", "resume", session, "--tracker", url, "-q", "--db",
                           f"sqlite:///{tmp_path / 'r.db'}"], capture_output=True, text=True, timeout=300, env=env)


def test_resume_to_the_tracker_on_a_new_port_and_refuse_another_tracker(tmp_path, monkeypatch, worlds):
    same, other = worlds
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    can_port = _free_port()
    emu = Emulator(same, can_port)
    try:
        def crash(done, total, text):
            if done == 20:
                emu.kill()  # the emulator process dies after 20 configurations

        out = start("correction_map", emu.robot, SERIAL, db=f"sqlite:///{tmp_path / 'r.db'}",
                    options={"tracker": emu.tracker, "grid": 1}, report=False, progress=crash)
    finally:
        emu.kill()
    assert out.status == "error" and out.exit_code == 2
    old_url = emu.tracker
    _, events = read_journal(out.folder / "journal.jsonl")
    kept = [e for e in events if e.type == "sample"]
    assert len(kept) == 20

    # it comes back with ANOTHER serial on a new port: refused in one line, nothing measured, nothing moved
    emu = Emulator(other, can_port)
    try:
        assert emu.tracker != old_url and emu.robot.startswith(f"canopen+socketcand://127.0.0.1:{can_port}")
        r = _resume(tmp_path, out.session, emu.tracker)
    finally:
        emu.kill()
    assert r.returncode == 2, r.stderr
    err = [line for line in r.stderr.splitlines() if line.startswith("station: error:")]
    assert len(err) == 1 and "LT-OTHER-0002" in err[0] and "LT-EMU-0001" in err[0], r.stderr
    _, events = read_journal(out.folder / "journal.jsonl")
    assert len([e for e in events if e.type == "sample"]) == 20

    # the same tracker (serial and model as journaled) on yet another port: the session completes
    emu = Emulator(same, can_port)
    try:
        r = _resume(tmp_path, out.session, emu.tracker)
    finally:
        emu.kill()
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "PASS"
    _, events = read_journal(out.folder / "journal.jsonl")
    moves = [e.data for e in events if e.type == "instrument_url"]
    assert [m["new"] for m in moves][-1] == emu.tracker and moves[0]["old"] == old_url
    assert {e.data["serial"] for e in events if e.type == "instrument"} == {"LT-EMU-0001"}
    samples = [e for e in events if e.type == "sample"]
    assert [s.seq for s in samples[:20]] == [s.seq for s in kept]  # the first 20 kept as journaled
    poses = [s.pose for s in samples]
    plan = json.loads(json.dumps([e for e in events if e.type == "plan"][0].plan))
    assert len(poses) == len(set(poses)) == len(plan["poses"])  # every configuration measured once
    assert {s.status["instrument"] for s in samples} == {"LT-EMU-0001"}
    rms = [e for e in events if e.type == "measurement" and e.name == "holdout_rms"][-1].value
    assert np.isfinite(rms) and rms < 0.1  # mm: the map holds across the restart (same world, same tracker)


def test_resume_tracker_option_needs_a_session_that_used_one(tmp_path, monkeypatch):
    """A session without an instrument cannot be redirected: one line, before any robot is opened."""
    from station.engine import events as ev
    from station.engine.runner import _instrument_urls
    from station.robot.errors import ConfigError

    header = ev.Header(session="s1", procedure="zero_offsets", procedure_path="/x.py", procedure_sha256="0" * 64,
                       procedure_title="", mode="procedure", serial="X", operator="o", station="h", url="ur://x",
                       model="ur5e", robot={}, limits={}, cell=None, options={"apply": False}, db=None, versions={})
    with pytest.raises(ConfigError, match="used no --tracker"):
        _instrument_urls(header, [], {"tracker": "tcp://127.0.0.1:1"})
    header.options["tracker"] = "tcp://127.0.0.1:1"
    moved = ev.Custom("instrument_url", {"option": "tracker", "old": "tcp://127.0.0.1:1", "new": "tcp://127.0.0.1:2"})
    opts, changes = _instrument_urls(header, [moved], None)  # a later resume keeps the last journaled address
    assert opts["tracker"] == "tcp://127.0.0.1:2" and changes == {}
    opts, changes = _instrument_urls(header, [moved], {"tracker": "tcp://127.0.0.1:3"})
    assert opts["tracker"] == "tcp://127.0.0.1:3" and changes == {"tracker": ("tcp://127.0.0.1:2", "tcp://127.0.0.1:3")}
    with pytest.raises(ConfigError, match="expected an instrument URL"):
        _instrument_urls(header, [], {"tracker": "127.0.0.1:3"})
