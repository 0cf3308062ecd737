"""Fault matrix, driver side (issue 9 item 7 / "Driver and bus faults" in docs/reliability.md): faults armed
from the WORLD FILE (``faults: [{do, device, count, at: {packet: {addr}}}]``), triggered by the phase's own
wire traffic, on the real Dynamixel wire (dynamixel-sdk on a pty). Every row asserts: the fault is one typed
``StationError`` line (the CLI's exit 2), the world's arm is not moving afterwards (ground truth), and a
fault within the documented retries is absorbed (no error, the phase completes)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml
from station.mocks.world import World, default_doc

from station.robot import ConnectionLost, DeviceFault, StationError, open_robot

PROFILE_ACCELERATION, HOMING_OFFSET, OPERATING_MODE = 108, 20, 11  # a move is one sync write from 108
PHASES = {  # phase -> (first write address of the phase, what the phase does)
    "motion": (PROFILE_ACCELERATION, lambda r, q0: r.move_joints(q0 + np.array([0.3, -0.2, 0.2, 0.3]))),
    "compliance": (OPERATING_MODE, lambda r, q0: (r.set_compliant(True), r.set_compliant(False))),
    "write-back": (HOMING_OFFSET, lambda r, q0: r.write_calibration({"offset.j2": 0.01})),
}
# fault -> (world-file fault entry without ``at``, expected error type or None = absorbed by retries)
FAULTS = {
    "timeout x1 (retried)": ({"do": "timeout", "device": 2, "count": 1}, None),
    "corrupt x1 (retried)": ({"do": "corrupt", "device": 2, "count": 1}, None),
    "timeout x4 (lost)": ({"do": "timeout", "device": 2, "count": 4}, ConnectionLost),
    "overload": ({"do": "device_fault", "device": 2, "code": 0x20}, DeviceFault),
    "bus disconnect": ({"do": "disconnect", "count": 1}, ConnectionLost),
}


def _world(tmp_path, fault: dict, addr: int) -> World:
    doc = default_doc("omx", seed=4)
    doc["motion"].update(time_mode="realtime")
    doc["faults"] = [{**fault, "at": {"packet": {"addr": addr}}}]
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    return World.from_file(path)


@pytest.mark.parametrize("phase", list(PHASES))
@pytest.mark.parametrize("fault", list(FAULTS))
def test_fault_in_phase(tmp_path, emulators, fault, phase):
    entry, expected = FAULTS[fault]
    addr, act = PHASES[phase]
    world = _world(tmp_path, entry, addr)
    emu = emulators("dynamixel", world)
    robot = open_robot(emu.url)
    try:
        robot.enable()
        q0 = robot.joint_positions().q
        if expected is None:
            act(robot, q0)  # within the documented retries: the phase completes
            assert world.faults.fired, "the armed fault never fired: the row tests nothing"
            return
        with pytest.raises(StationError) as e:
            act(robot, q0)
            robot.joint_positions()  # a fault may bite on the phase's last answer or the next one
        assert isinstance(e.value, expected), repr(e.value)
        assert "\n" not in str(e.value) and str(e.value)
        time.sleep(0.3)
        assert not world.is_moving()  # stopped / safe: the truth, not the driver's word
    finally:
        robot.close()


def test_world_file_fault_waits_for_its_packet(tmp_path):
    world = _world(tmp_path, {"do": "timeout", "device": 1}, HOMING_OFFSET)
    assert not world.faults.take("timeout", 1)  # not armed before the write-back's first write
    world.faults.notice(packet={"addr": PROFILE_ACCELERATION})
    assert not world.faults.take("timeout", 1)
    world.faults.notice(packet={"addr": HOMING_OFFSET})
    assert world.faults.take("timeout", 1)


def test_world_file_bad_fault_is_one_line(tmp_path):
    from station.mocks.world import WorldFileError

    doc = default_doc("omx", seed=4)
    doc["faults"] = [{"do": "explode"}]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(WorldFileError, match=r"faults\[0\]\.do.*'explode' is not one of timeout"):
        World.from_file(path)


def test_compliance_left_by_a_crash_is_reported_and_reset(tmp_path, emulators):
    """Issue 9 item 8: a run killed while seating leaves the servos compliant (current-based position mode);
    the next connection reports it (status().compliant, what the pre-run check reads) and set_compliant(False)
    makes the arm stiff again. Truth: the world's compliance."""
    world = World.default(model="omx", seed=4, time_mode="realtime")
    emu = emulators("dynamixel", world)
    crashed = open_robot(emu.url)
    crashed.enable()
    crashed.set_compliant(True)
    crashed.bus.close()  # kill -9: no teardown, the port just goes away
    crashed._closed = True
    assert world.compliant
    with open_robot(emu.url) as robot:
        assert robot.status().compliant
        robot.set_compliant(False)
        assert not robot.status().compliant and not world.compliant
