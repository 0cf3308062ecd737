"""``station mock dynamixel`` as a process: prints a pty path the real SDK opens; EEPROM file = power cycle."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
import yaml
from clirunner import ChildProcess, station_proc, station_spawn
from station.mocks.world import World

from station.robot import open_robot


def _start(*args: str) -> tuple[ChildProcess, str]:
    proc = station_spawn("mock", "dynamixel", *args)
    line = proc.readline(timeout=30)
    if not line:
        proc.close()
        pytest.fail("station mock dynamixel printed nothing within 30 s")
    return proc, line.strip()


def _stop(proc: ChildProcess) -> int:
    with proc:
        proc.send_signal(signal.SIGTERM)
        return proc.wait(timeout=10).code


def test_process_serves_world_file_and_keeps_eeprom_across_restarts(tmp_path: Path):
    world = World.default(model="omx", seed=11, start=[0.3, -0.4, 0.5, -0.2], time_mode="realtime",
                          buses={"dynamixel": {"ids": "21-24", "contact_id": 201}})
    wfile = tmp_path / "world.yaml"
    wfile.write_text(yaml.safe_dump(world.to_dict()))
    truth = World.from_file(wfile).encoder_q()
    eeprom = tmp_path / "eeprom.json"
    proc, path = _start("--world", str(wfile), "--ids", "21-24", "--contact-id", "200", "--eeprom", str(eeprom))
    try:
        assert path.startswith("/dev/pts/")
        with open_robot(f"dynamixel://{path}?ids=21-24&model=omx&contact=200&latency=50") as robot:
            snap = robot.joint_positions()
            tick = 1 / world.nominal.joints[0].encoder.counts_per_unit
            assert np.all(np.abs(snap.q - truth) <= tick / 2 + 1e-12)
            robot.write_calibration({"offset.j3": 0.05})
            written = robot.read_calibration()
    finally:
        assert _stop(proc) == 0
    assert json.loads(eeprom.read_text())["format"] == "station-dxl-eeprom/1"
    proc, path = _start("--world", str(wfile), "--eeprom", str(eeprom))  # ids from the world's buses section
    try:
        with open_robot(f"dynamixel://{path}?ids=21-24&model=omx&contact=201&latency=50") as robot:
            assert robot.read_calibration() == written
    finally:
        assert _stop(proc) == 0


def test_bad_arguments_exit_2_with_one_line():
    r = station_proc("mock", "dynamixel", "--ids", "1-3", timeout=60)
    assert r.code == 2
    assert r.err.strip().startswith("station: error:") and "one id per joint" in r.err
    assert r.out == ""


def test_two_worlds_print_two_serials_and_the_robot_reports_the_printed_one(tmp_path):
    """X-series servos carry no serial number: without ``serial=`` every omx arm on ids 11-14 would file its
    records under one derived serial (two arms merged, a false DRIFT). The printed URL carries one derived from
    the world (or the world's ``buses.dynamixel.serial``), and the driver reports it as configured."""
    from station.mocks.world.example import example_text

    urls = []
    for seed, extra in ((1, None), (2, None), (2, "ARM-7")):
        doc = yaml.safe_load(example_text("omx", seed=seed))
        if extra:
            doc.setdefault("buses", {}).setdefault("dynamixel", {})["serial"] = extra
        (tmp_path / f"w{seed}{extra}.yaml").write_text(yaml.safe_dump(doc))
        proc, _ = _start("--world", str(tmp_path / f"w{seed}{extra}.yaml"))
        try:
            urls.append(proc.readline(timeout=30).strip().removeprefix("robot URL "))
            with open_robot(urls[-1]) as robot:
                ident = robot.identity()
            assert ident.serial_source == "url" and urls[-1].endswith(f"serial={ident.serial}")
        finally:
            _stop(proc)
    serials = [u.rsplit("serial=", 1)[1] for u in urls]
    assert serials[0] != serials[1] and serials[0].startswith("DXL-") and serials[2] == "ARM-7", serials
