"""`station jog` argument errors: one line, exit 2, no session folder left behind."""

from __future__ import annotations

import pytest
from clirunner import station_proc

from station.cli.jog_cmd import url_with_model


def _station(*args, cwd):
    # a bare environment: no terminal, no inherited STATION_* settings
    return station_proc(*args, cwd=cwd, timeout=60, env={"STATION_HOME": str(cwd / "home"), "PATH": "/usr/bin:/bin"},
                        replace_env=True)


@pytest.mark.parametrize("args, message", [
    (["--robot", "nosuch://x"], "unknown scheme 'nosuch'"),
    (["--robot", "dynamixel:///dev/null?model=omx", "--reference", "1,2"], "--reference '1,2'"),
])
def test_bad_arguments_exit_2(tmp_path, args, message):
    p = _station("jog", *args, cwd=tmp_path)
    assert p.code == 2, p.err
    lines = p.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("station: error:") and message in lines[0], p.err
    assert not (tmp_path / "home").exists()


def test_model_goes_into_the_url():
    assert url_with_model("canopen+virtual://c0?nodes=1-6", "arm6") == "canopen+virtual://c0?nodes=1-6&model=arm6"
    assert url_with_model("dynamixel:///dev/ttyUSB0?ids=1-4&model=x", "omx").endswith("ids=1-4&model=omx")
    assert url_with_model("ur://h", None) == "ur://h"


def test_serial_and_identify_checked_before_any_session(tmp_path):
    from station.mocks.dynamixel import DynamixelEmulator
    from station.mocks.world import World

    emu = DynamixelEmulator(World.default(model="omx", seed=1), ids=[11, 12, 13, 14])
    path = emu.start().path
    try:
        # a serial the URL configures must match (a serial derived from servo ids is no robot serial)
        p = _station("jog", "--robot", f"dynamixel://{path}?ids=11-14&model=omx&serial=OMX-7", "--serial",
                     "NOT-THIS-ONE", cwd=tmp_path)
        bad = _station("jog", "--robot", f"dynamixel://{path}?ids=11-14&model=omx", "--identify", "offsets,wings",
                       cwd=tmp_path)
    finally:
        emu.stop()
    assert bad.code == 2 and "--identify" in bad.err and "wings" in bad.err, bad.err
    assert len(bad.err.strip().splitlines()) == 1
    assert p.code == 2 and "reports serial" in p.err and "NOT-THIS-ONE" in p.err, p.err
    assert len(p.err.strip().splitlines()) == 1
    assert not (tmp_path / "home").exists()


def test_jog_without_serial_and_without_a_terminal_is_refused(tmp_path):
    """The session is filed under a serial the technician confirms: with no --serial and no terminal to ask
    on (and a Dynamixel bus, whose only ids are device ids), one line, exit 2, no session folder."""
    from station.mocks.dynamixel import DynamixelEmulator
    from station.mocks.world import World

    emu = DynamixelEmulator(World.default(model="omx", seed=2), ids=[11, 12, 13, 14])
    path = emu.start().path
    try:
        p = _station("jog", "--robot", f"dynamixel://{path}?ids=11-14&model=omx", cwd=tmp_path)
    finally:
        emu.stop()
    assert p.code == 2, p.err
    assert p.err.strip().splitlines()[-1].startswith("station: error: --serial is required")
    assert "Traceback" not in p.err
    sessions = tmp_path / "home" / "sessions"
    assert not sessions.exists() or not any(sessions.iterdir())
