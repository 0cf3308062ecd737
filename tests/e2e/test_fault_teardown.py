"""Safe teardown after a bus fault: a CANopen bus-off while the arm is seated (compliant,
every drive enabled in profile torque mode). The station's controller is off the bus for its recovery time,
so the quick stop sent when the fault latched never reaches the drives (the emulator drops frames sent while
bus-off); teardown's "compliance off" must then disable every drive (power stage off, brakes engaged) through
whatever path works and say so. Ground truth: the emulated drives' CiA 402 states and the world's enables."""

from __future__ import annotations

import time

import pytest
from station.mocks.world import World

from station.robot import BusError

START = [0.3, -0.7, 0.9, 1.0, -0.6, 2.0]
SAFE = ("SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON")


@pytest.fixture
def seated(robot_rig):
    world = World.default(model="arm6", seed=11, start=START, time_mode="realtime")
    emu, robot = robot_rig("canopen", world)
    robot.set_compliant(True)
    assert world.compliant
    return world, emu, robot


def _states(emu) -> list[str]:
    from station.drivers.canopen.cia402 import state_of
    return [state_of(int(d.get(0x6041))) for d in emu.drives.values()]


def test_bus_off_while_seated_teardown_disables_every_drive(seated):
    world, emu, robot = seated
    emu.busoff_recovery = 0.3
    emu.inject_error_frame("busoff")
    time.sleep(0.1)
    # the bus-off controller's quick stop was lost: the drives are still enabled and compliant
    assert all(s == "OPERATION ENABLED" for s in _states(emu)) and world.compliant
    t0 = time.monotonic()
    with pytest.raises(BusError) as e:
        robot.set_compliant(False)  # what the engine's teardown calls
    took = time.monotonic() - t0
    msg = str(e.value)
    assert "bus-off" in msg and "compliance off not possible" in msg
    assert "every drive disabled instead" in msg and "\n" not in msg
    assert all(s in SAFE for s in _states(emu)), _states(emu)
    assert not world.enabled().any() and not world.compliant
    assert took < 1.5  # bounded: recovery 0.3 s + a few SYNC rounds


def test_drives_that_stay_unreachable_are_reported_loudly(seated):
    world, emu, robot = seated
    emu.busoff_recovery = 60.0  # the controller never comes back within teardown
    emu.inject_error_frame("busoff")
    time.sleep(0.05)
    t0 = time.monotonic()
    with pytest.raises(BusError) as e:
        robot.set_compliant(False)
    assert time.monotonic() - t0 < 3.0  # bounded, never a hang
    msg = str(e.value)
    assert "drives NOT confirmed disabled on nodes [1, 2, 3, 4, 5, 6]" in msg
    assert "switch off drive power at the cabinet" in msg
    # the truth the message cannot know: the station's heartbeat does not reach the drives either, so each one's
    # consumer (0x1016, 800 ms by default) quick-stops its joint by itself
    end = time.monotonic() + 2.0
    while any(s == "OPERATION ENABLED" for s in _states(emu)) and time.monotonic() < end:
        time.sleep(0.02)
    assert all(s in ("QUICK STOP ACTIVE", *SAFE) for s in _states(emu)), _states(emu)
    assert not world.is_moving()


def test_a_closed_socketcand_link_is_reported_not_waited_out_twice(caplog):
    """The socketcand server goes away (the connection is closed: it cannot come back on this bus). The fault's
    own attempt to disable the drives reports loudly what it could not confirm; close() then says so again at
    once instead of waiting out a second attempt (2 x the heartbeat consumer time each)."""
    import uuid

    from station.mocks.canopen.emulator import CanopenEmulator
    from station.mocks.canopen.hub import SocketcandHub
    from station.mocks.world import World

    from station.robot import ConnectionLost, StationError, open_robot

    chan = f"d-{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(World.default(model="arm6", seed=7, start=START), channel=chan).start()
    hub = SocketcandHub(chan, port=0).start()
    try:
        robot = open_robot(f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6")
        robot.enable()
        hub.stop()  # the server closes every connection
        deadline = time.monotonic() + 5.0
        while robot.faults.error is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert isinstance(robot.faults.error, ConnectionLost), robot.faults.error
        with pytest.raises(StationError) as e:
            robot.set_compliant(False)  # what the engine's teardown calls: the drives' safe state, attempted
        assert "drives NOT confirmed disabled" in str(e.value)
        caplog.clear()
        t0 = time.monotonic()
        with caplog.at_level("WARNING", logger="station.drivers.canopen"):
            robot.close()
        took = time.monotonic() - t0
        assert took < 0.8, took  # a second attempt would take 2 x 0.8 s
        loud = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert any("NOT confirmed disabled" in m and "is closed" in m for m in loud), loud
    finally:
        hub.stop()
        emu.stop()
