"""``station resume SESSION --tracker URL``: which instrument address a resume uses (the journal's, replaced in order
by every journaled ``instrument_url``, then the one given). End to end, with the emulator process killed and the
tracker restarted on another port: tests/procedures/test_correction_map_calibration.py."""

import pytest
from clirunner import station_proc


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
    planted = ev.Custom("instrument_url", {"option": "apply", "old": False, "new": "tcp://x:1"})
    assert _instrument_urls(header, [planted], None)[0]["apply"] is False  # only URL options are ever replaced


def test_run_calibration_option_is_checked_before_the_robot_is_opened(tmp_path):
    """``station run correction_map --calibration FILE``: a missing or malformed file is one line, exit 2, before
    the robot URL is even opened (a robot that does not exist: the error names the file, not the bus)."""

    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "station-calibration/1", "units": "SI (m, rad)", "model": "arm6"}')
    for cal, expect in ((tmp_path / "none.json", "calibration"), (bad, "parameters")):
        r = station_proc("run", "correction_map", "--robot", "canopen+socketcand://127.0.0.1:9?channel=can0&model=arm6",
                         "--serial", "X", "--tracker", "tcp://127.0.0.1:9", "--calibration", cal, "-q", "--db",
                         f"sqlite:///{tmp_path / 'r.db'}", timeout=60, env={"STATION_HOME": str(tmp_path / "home")})
        assert r.code == 2, r.err
        lines = r.err_lines
        assert len(lines) == 1 and lines[0].startswith("station: error: calibration ") and str(cal) in lines[0]
        assert expect in lines[0], lines
