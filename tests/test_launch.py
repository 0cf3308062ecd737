"""The one emulator launcher (``station.mocks.launch``): the URL it hands out opens the robot the world file
describes, on every bus and in both process modes; children never outlive their parent."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from station.mocks.errors import MockError
from station.mocks.launch import launch
from station.mocks.world import World

from station.robot import open_robot

STATION = str(Path(sys.executable).with_name("station"))


def _world_file(tmp_path: Path, model: str, buses: dict) -> Path:
    world = World.default(model=model, seed=4, buses=buses)
    path = tmp_path / f"{model}.yaml"
    path.write_text(yaml.safe_dump(world.to_dict()))
    return path


@pytest.mark.parametrize("process", [False, True])
def test_dynamixel_url_follows_the_world_files_bus_settings(tmp_path, emulators, process):
    path = _world_file(tmp_path, "omx", {"dynamixel": {"ids": "21-24", "contact_id": 201}})
    emu = emulators("dynamixel", path, serial="OMX 7/1", process=process)
    assert emu.url.startswith(f"dynamixel://{emu.port}?") and "serial=OMX%207%2F1" in emu.url
    with open_robot(emu.url + "&latency=50") as robot:
        ident = robot.identity()
        assert [d["id"] for d in ident.devices] == [21, 22, 23, 24, 201]  # servos and the contact sensor
        assert ident.serial == "OMX 7/1" and robot.touch() is False
        truth = World.from_file(path).encoder_q()
        tick = 1 / robot.model.joints[0].encoder.counts_per_unit
        assert abs(robot.joint_positions().q - truth).max() <= tick / 2 + 1e-12


def test_canopen_in_process_serves_the_world_object(emulators):
    world = World.default(model="arm6", seed=2, buses={"canopen": {"nodes": [3, 4, 5, 6, 7, 8]}})
    emu = emulators("canopen", world, serial="A6-9")
    assert emu.world is world and "nodes=3,4,5,6,7,8" in emu.url
    with open_robot(emu.url) as robot:
        assert [d["node"] for d in robot.identity().devices] == [3, 4, 5, 6, 7, 8]
        assert robot.identity().serial == "A6-9"


def test_ur_child_on_a_random_loopback_address(tmp_path, emulators):
    path = _world_file(tmp_path, "ur5e", {"ur": {"serial": "20235512345"}})
    a, b = emulators("ur", path), emulators("ur", path)
    assert a.host != b.host and a.host.startswith("127.") and a.url == f"ur://{a.host}?model=ur5e&power_on=yes"
    assert a.dashboard("get serial number") == "20235512345"


def test_bad_requests_are_refused():
    with pytest.raises(MockError, match="no emulator for bus 'profibus'"):
        launch("profibus")
    with pytest.raises(ValueError, match="child process only"):
        launch("ur", process=False)


def test_a_child_ends_with_its_parent(tmp_path):
    """A test process killed with -9 leaves no emulator behind (``--exit-with-parent``)."""
    path = _world_file(tmp_path, "omx", {})
    code = ("import sys, time; from station.mocks.launch import launch\n"
            f"emu = launch('dynamixel', {str(path)!r}, process=True).start()\n"
            "print(emu.proc.pid, flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        os.kill(parent.pid, 9)
        parent.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and _alive(child):
            time.sleep(0.1)
        assert not _alive(child)
    finally:
        if parent.poll() is None:
            parent.kill()
        parent.stdout.close()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_station_demo_with_an_unknown_bus_is_one_line():
    p = subprocess.run([STATION, "demo", "--robot", "profibus"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    from station.mocks.plug import demo_buses

    assert p.stderr.strip().splitlines() == [f"station: error: --robot must be one of {', '.join(demo_buses())}, "
                                             "got 'profibus'"]
