"""Write-back as a transaction on the Dynamixel emulator (pty, real dynamixel_sdk), the station in its
own process: SIGTERM in the write window is held off until every servo is written and read back; kill -9 in
the window leaves a half-written calibration that ``station resume`` finishes and ``station restore`` rolls
back to the journaled backup.

The write window is widened, not faked: a wrapper around the station's entry point splits the driver's own
``write_calibration`` into two real writes (joints 1-2, then 3-4) with a pause between them, so a signal lands
where a real one would have to be lucky to land."""

import contextlib
import json
import os
import signal
import time

import pytest
import yaml
from clirunner import station_proc, station_spawn
from station.mocks.launch import launch

from station.cli.run_cmd import write_demo_files
from station.engine import read_journal
from station.robot import open_robot

# the station child's preludes (tests/clirunner.py); MARKER is the file they write when the window opens
WRAPPER = """
import time
from pathlib import Path
from station.drivers.dynamixel.robot import DynamixelRobot
orig = DynamixelRobot.write_calibration
marker = Path(MARKER)
def split_write(self, values):
    items = sorted(values.items())
    orig(self, dict(items[:2]))
    marker.write_text("half")
    time.sleep(4.0)
    orig(self, dict(items[2:]))
DynamixelRobot.write_calibration = split_write
"""


def _device(url):
    robot = open_robot(url)
    try:
        return robot.read_calibration()
    finally:
        robot.close()


def _close(want, have, tol=0.8e-3):  # half an XM430 tick (1.53e-3 rad): the device stores whole ticks
    return all(abs(have[k] - v) < tol for k, v in want.items())


def _can_pause_wrapper(condition: str, note: str) -> str:
    """A station entry point whose CANopen write-back pauses 4 s (after writing the marker file) at the first
    SDO write for which ``condition`` (on node_id, index) holds: a window a signal can land in."""
    return f"""
import time
from pathlib import Path
from station.drivers.canopen.robot import CanopenRobot
marker = Path(MARKER)
orig = CanopenRobot.write_calibration
def write_calibration(self, values):
    real, real_obj = self.bus.sdo_write, self.bus.write_obj
    def pause(node_id, index):
        if {condition} and not marker.exists():
            marker.write_text({note!r})
            time.sleep(4.0)
    def sdo_write(node_id, index, value, sub=None, **kw):
        pause(node_id, index)
        return real(node_id, index, value, sub=sub, **kw)
    def write_obj(node_id, index, sub, kind, value, **kw):
        pause(node_id, index)
        return real_obj(node_id, index, sub, kind, value, **kw)
    self.bus.sdo_write, self.bus.write_obj = sdo_write, write_obj
    try:
        return orig(self, values)
    finally:
        self.bus.sdo_write, self.bus.write_obj = real, real_obj
CanopenRobot.write_calibration = write_calibration
"""


# every drive has its new zero (homing on the current position), drives 1-3 have stored it, 4-6 not yet: after a
# power cycle of the drives (what a kill -9 test adds) 1-3 hold the new zero, 4-6 the old one
CAN_SPLIT_WRAPPER = _can_pause_wrapper("index == 0x1010 and node_id == 4", "half")


class Rig:
    def __init__(self, url, args, wrapper, tol, n_first, env, tmp, after_kill=None):
        self.url, self.args, self.wrapper, self.tol, self.n_first, self.env, self.tmp = (
            url, args, wrapper, tol, n_first, env, tmp)
        self.after_kill = after_kill  # what a kill -9 leaves to happen to the device (CANopen: its power cycle)


@pytest.fixture(params=["dynamixel", "canopen"])
def bench(request, tmp_path):
    """The write window on both buses that store calibration in the device: Dynamixel (pty, dynamixel_sdk;
    servos 1-2 written, 3-4 not) and CANopen (socketcand, python-can + canopen; drives 1-3 stored, 4-6 homed but
    not stored: a kill -9 there followed by the drives' power cycle leaves 1-3 new and 4-6 old)."""
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    db = f"sqlite:///{tmp_path / 'r.db'}"
    if request.param == "dynamixel":
        # hidden zero offsets of 0.6-2 deg (7-23 ticks): old and new values differ on every servo
        world_path, cell_path, serial = write_demo_files("dynamixel", tmp_path, seed=41, time_mode="instant")
        doc = yaml.safe_load(world_path.read_text())
        doc["errors"]["explicit"] = {"offset.j1": 0.021, "offset.j2": -0.015, "offset.j3": 0.011,
                                     "offset.j4": -0.018}
        world_path.write_text(yaml.safe_dump(doc))
        with launch("dynamixel", world_path, serial=serial, process=True) as emu:  # its own GIL, like a servo
            yield Rig(emu.url, ["run", "zero_offsets", "--robot", emu.url, "--serial", serial, "--cell",
                                str(cell_path), "--reference", "cell", "--cone", "70", "--apply", "-q", "--db", db,
                                "--poses", "12", "--holdout", "2"], WRAPPER, 0.8e-3, 2, env, tmp_path)
        return
    with _can(tmp_path, 44) as (emu, url, cell_path, serial):
        def power_cycle():
            emu.power_cycle()
            time.sleep(0.3)

        yield Rig(url, ["run", "zero_offsets", "--robot", url, "--serial", serial, "--cell", str(cell_path),
                        "--apply", "-q", "--db", db, "--poses", "12", "--holdout", "2"], CAN_SPLIT_WRAPPER,
                  1e-6, 3, env, tmp_path, after_kill=power_cycle)


@contextlib.contextmanager
def _can(tmp_path, seed):
    import uuid

    from station.mocks.canopen.emulator import CanopenEmulator
    from station.mocks.canopen.hub import SocketcandHub
    from station.mocks.world import World

    world_path, cell_path, serial = write_demo_files("canopen", tmp_path, seed=seed, time_mode="instant")
    chan = f"d-{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(World.from_file(world_path), channel=chan).start()
    hub = SocketcandHub(chan, port=0).start()
    try:
        # not an SDO timing test: the drives run in this (busy) process behind the hub, so SDO answers may wait
        # for the CPU longer than the production 300 ms (sdo_timeout_ms is the documented URL option)
        url = f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6&sdo_timeout_ms=2000"
        yield emu, url, cell_path, serial
    finally:
        hub.stop()
        emu.stop()


def _until_window(start_args, env, marker, home, sig, wrapper=None, tries=4):
    """Run (then, after a bus fault before the write window, resume: the supported way on after a fault) until
    the wrapper signals the write window; then send ``sig``. On a loaded machine a lost bus answer can end a
    try early (the drivers' retries); every try is journaled in the same session."""
    args = start_args
    prelude = f"MARKER = {str(marker)!r}\n{wrapper or WRAPPER}"
    for _ in range(tries):
        with station_spawn(*args, env=env, prelude=prelude) as proc:
            end = time.monotonic() + 240
            while not marker.exists() and proc.running() and time.monotonic() < end:
                time.sleep(0.02)
            if marker.exists():
                t0 = time.monotonic()
                proc.send_signal(sig)
                r = proc.wait(timeout=60)
                journal = next((home / "sessions").glob("*/journal.jsonl"))
                return r.code, r.out, r.err, time.monotonic() - t0, journal
            r = proc.wait(timeout=30)
            assert r.code == 2 and "station resume" in r.err, (r.out, r.err)  # a fault: resume
        args = ["resume", next((home / "sessions").glob("*/journal.jsonl")).parent.name, "-q"]
    raise AssertionError(f"never reached the write window in {tries} tries: {r.err}")


def _run_until_window(rig, sig):
    return _until_window(rig.args, rig.env, rig.tmp / "in-window", rig.tmp / "home", sig, rig.wrapper)


def _writebacks(journal):
    return [e for e in read_journal(journal)[1] if e.type == "writeback"]


def test_sigterm_in_the_write_window_is_held_until_every_servo_is_written(bench):
    rig = bench
    before = _device(rig.url)
    rc, stdout, stderr, took, journal = _run_until_window(rig, signal.SIGTERM)
    assert rc == 130, stderr
    assert took > 2.0  # it waited for the rest of the write (the wrapper's 4 s pause), then stopped
    wb = _writebacks(journal)
    assert [e.phase for e in wb] == ["pre-image", "written"]
    after = wb[0].after
    assert _close(after, _device(rig.url), rig.tol) and not _close(before, after, rig.tol)  # all new values
    assert _close(before, json.loads((journal.parent / "calibration-backup.json").read_text())["before"], rig.tol)
    assert stderr.strip().splitlines()[-1].startswith("station: interrupted; continue with: station resume ")
    assert "Traceback" not in stderr
    # resume: the write is journaled complete; the known-pose check runs, PASS
    again = station_proc("resume", journal.parent.name, "-q", env=rig.env, timeout=240)
    assert again.code == 0 and again.out.strip().splitlines()[-1] == "PASS", again.err
    wb = _writebacks(journal)
    assert wb[-1].phase == "verified" and wb[-1].verified
    assert _close(after, _device(rig.url), rig.tol)


@pytest.mark.parametrize("then", ["resume", "restore"])
def test_kill_9_in_the_write_window_is_finished_or_rolled_back(bench, then):
    rig = bench
    env, tol, k = rig.env, rig.tol, rig.n_first
    before = _device(rig.url)
    rc, stdout, stderr, took, journal = _run_until_window(rig, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    (pre,) = _writebacks(journal)
    assert pre.phase == "pre-image"
    if rig.after_kill is not None:
        rig.after_kill()
    half = _device(rig.url)
    names = sorted(pre.after)
    assert _close({n: pre.after[n] for n in names[:k]}, half, tol)  # the first joints new ...
    assert _close({n: pre.before[n] for n in names[k:]}, half, tol)  # ... the others old: half written
    assert not _close(pre.after, half, tol)
    if then == "resume":
        again = station_proc("resume", journal.parent.name, "-q", env=env, timeout=240)
        assert again.code == 0 and again.out.strip().splitlines()[-1] == "PASS", again.err
        wb = _writebacks(journal)
        assert [e.phase for e in wb] == ["pre-image", "written", "verified"] and wb[-1].verified
        assert "finished on resume" in wb[1].note
        assert _close(pre.after, _device(rig.url), tol)  # all new values stored
    else:
        r = station_proc("restore", journal.parent.name, env=env, timeout=120)
        assert r.code == 0, r.err
        assert "restored" in r.out
        assert _close(before, _device(rig.url), tol)  # the pre-image, to the count
        wb = _writebacks(journal)
        assert [(e.kind, e.phase) for e in wb[1:]] == [("restore", "pre-image"), ("restore", "written")]
        # the session's write-back was rolled back on purpose: resume says so in one line, nothing moves
        again = station_proc("resume", journal.parent.name, "-q", env=env, timeout=120)
        err = again.err
        assert again.code == 2 and err.strip().count("\n") == 0 and "station restore" in err, err


def test_restore_without_a_backup_is_one_line_before_the_robot_is_opened(tmp_path):
    from station.engine import events as ev
    from station.engine.journal import Journal

    folder = tmp_path / "home" / "sessions" / "S-1"
    Journal.create(folder / "journal.jsonl", ev.Header(session="S-1", procedure="zero_offsets", serial="X",
                                                       url="dynamixel:///dev/does-not-exist?model=omx")).close()
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    r = station_proc("restore", "S-1", env=env, timeout=60)
    err = r.err
    assert r.code == 2 and err.count("\n") == 1 and "no backup" in err and "does-not-exist" not in err, err


# ---- CANopen: killed after the 0x607C writes, before the 0x1010 store --------------------------
# every 0x607C sent, the store not yet
CAN_WRAPPER = _can_pause_wrapper("index == 0x1010", "home offsets written, store not sent")


@pytest.fixture
def can_bench(tmp_path):
    """CiA 402 drives behind a socketcand hub (python-can's real socketcand client), so the station can run
    in its own process and be killed."""
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    with _can(tmp_path, 43) as (emu, url, cell_path, serial):
        yield emu, url, cell_path, serial, env, tmp_path


def test_canopen_kill_9_before_the_store_is_finished_by_resume_and_survives_a_power_cycle(can_bench):
    emu, url, cell_path, serial, env, tmp = can_bench
    before = _device(url)
    rc, _, _, _, journal = _until_window(
        ["run", "zero_offsets", "--robot", url, "--serial", serial, "--cell", str(cell_path), "--apply", "-q",
         "--poses", "12", "--holdout", "2", "--db", f"sqlite:///{tmp / 'r.db'}"], env, tmp / "in-window",
        tmp / "home", signal.SIGKILL, CAN_WRAPPER)
    assert rc == -signal.SIGKILL
    (pre,) = _writebacks(journal)
    tol = 1e-6  # arm6 encoders: ~1e-6 rad per count
    assert _close(pre.after, _device(url), tol)  # the drives answer with the new values: volatile only
    # resume finishes the transaction: the values are written again, this time with the 0x1010 store
    again = station_proc("resume", journal.parent.name, "-q", env=env, timeout=300)
    assert again.code == 0 and again.out.strip().splitlines()[-1] == "PASS", again.err
    wb = _writebacks(journal)
    assert [e.phase for e in wb] == ["pre-image", "written", "verified"] and wb[-1].verified
    emu.power_cycle()  # what is not stored is lost here
    time.sleep(0.5)
    assert _close(pre.after, _device(url), tol) and not _close(before, pre.after, tol)
