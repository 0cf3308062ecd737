"""Bad input and bus faults reach the user as exactly one line and exit 2 (no library narration)."""

from clirunner import station_proc

ABSENT_ARM = "canopen+virtual://nobody-here?nodes=1-6&model=arm6"  # a bus with no drive on it


def test_missing_cell_file_fails_before_the_robot_is_opened(tmp_path):
    r = station_proc("run", "zero_offsets", "--robot", ABSENT_ARM, "--serial", "S1",
                     "--cell", tmp_path / "absent.yaml", timeout=60)
    rc, lines = r.code, r.err_lines
    assert rc == 2
    assert len(lines) == 1 and "cell file" in lines[0] and "absent.yaml" in lines[0], lines


def test_silent_bus_is_one_line_without_library_logging(tmp_path):
    cell = tmp_path / "cell.yaml"
    cell.write_text("format: station-cell/1\nunits: {length: mm}\npoints:\n"
                    "  A: {kind: socket, position: [350, 0, 750], approach: [0, 0, 1]}\n")
    import os

    env = {k: v for k, v in os.environ.items() if k != "STATION_DEBUG"} | {"STATION_HOME": str(tmp_path / "h")}
    r = station_proc("run", "zero_offsets", "--robot", ABSENT_ARM, "--serial", "S1", "--cell", cell, env=env,
                     replace_env=True, timeout=60)
    rc, lines = r.code, r.err_lines
    assert rc == 2
    assert len(lines) == 1 and lines[0].startswith("station: error:") and "does not answer" in lines[0], lines


def test_serial_rules():
    """A serial the robot reports or the URL configures must match; one derived from device ids is replaced."""
    import pytest

    from station.robot import ConfigError, Identity, adopt_serial

    derived = Identity(vendor="v", model="arm6", serial="00000A5E-5A100001", serial_source="derived")
    assert adopt_serial(derived, "LINE3-0042").serial == "LINE3-0042"
    assert adopt_serial(derived, "LINE3-0042").serial_source == "operator"
    for source in ("robot", "url"):
        ident = Identity(vendor="v", model="ur5e", serial="20235500000", serial_source=source)
        assert adopt_serial(ident, "20235500000") is ident
        with pytest.raises(ConfigError, match="reports serial"):
            adopt_serial(ident, "OTHER")


def _run_arm6(tmp_path, monkeypatch, procedure: str, **kw):
    """``procedure`` on the demo's emulated arm6 (CANopen, instant motion, one socket): the run's Outcome."""
    from station.mocks.launch import launch

    from station.api import run as start
    from station.cli.run_cmd import write_demo_files

    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world_path, cell_path, serial = write_demo_files("canopen", tmp_path / "demo", 5, "instant")
    with launch("canopen", world_path, serial=serial, process=False) as emu:
        return start(procedure, emu.url, serial, cell=cell_path, db=f"sqlite:///{tmp_path / 'r.db'}", **kw)


def test_dh_full_with_one_socket_is_refused_with_a_reason(tmp_path, monkeypatch):
    """Full link geometry from one unknown point is unobservable: the procedure says so instead of a FAIL."""
    out = _run_arm6(tmp_path, monkeypatch, "dh_full")
    assert out.status == "error" and out.exit_code == 2
    assert "at least 3 reference sockets" in str(out.error)


def test_poses_below_the_unknowns_refused_before_motion(tmp_path, monkeypatch):
    """zero_offsets on a 6-joint arm with an unknown socket: 6 offsets + 3 point coordinates = 9 unknowns
    (6 joints of arm6 + one socket); --poses 8 is refused before anything is planned or touched."""
    from station.engine.journal import read_journal

    out = _run_arm6(tmp_path, monkeypatch, "zero_offsets", options={"n_fit": 8})
    assert out.status == "error" and out.exit_code == 2
    assert "--poses 8" in str(out.error) and "9 unknowns" in str(out.error) and "\n" not in str(out.error)
    _, events = read_journal(out.folder / "journal.jsonl")
    assert not [e for e in events if e.type in ("sample", "plan")]  # nothing planned, nothing touched
