"""Every CAN adapter python-can speaks, as ``canopen+<interface>://<channel>?bitrate=...`` (python-can's own
``can.Bus(interface=...)`` underneath): registered as station.robots entry points; virtual and socketcand run
against the emulator (test_canopen_driver.py, test_canopen_socketcand.py); for the adapters this
machine has no library or hardware for, one error line naming the interface and what to install, exit 2."""

from __future__ import annotations

import os
import socket

import can
import pytest
from can.interfaces.virtual import VirtualBus
from clirunner import station_proc
from station.drivers.canopen import CanopenRobot

from station.kinematics import load_model
from station.robot import ConfigError, ConnectionLost, StationError, open_robot
from station.robot.registry import driver_class, schemes

Q = "nodes=1-6&model=arm6&bitrate=500000"


def _has_socketcan() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError):
        return False
    return True


def test_every_interface_is_a_registered_scheme():
    for name in ("socketcan", "pcan", "kvaser", "ixxat", "slcan", "virtual", "socketcand"):
        assert f"canopen+{name}" in schemes()
        assert driver_class(f"canopen+{name}") is CanopenRobot


@pytest.mark.parametrize("url, words", [
    (f"canopen+pcan://PCAN_USBBUS1?{Q}", ("canopen+pcan", "PCAN-Basic")),
    (f"canopen+kvaser://0?{Q}", ("canopen+kvaser", "CANlib")),
    (f"canopen+ixxat://0?{Q}", ("canopen+ixxat", "IXXAT VCI")),
    (f"canopen+slcan:///dev/ttyACM97?{Q}", ("slcan", "/dev/ttyACM97", "pyserial")),
])
def test_an_adapter_without_its_library_or_hardware_is_one_line(url, words):
    """This machine has none of these adapters nor their vendor libraries: the error names the interface and
    what it needs (the vendor driver or pip package), in one line, before anything else happens."""
    with pytest.raises(StationError) as e:
        open_robot(url)
    assert isinstance(e.value, ConfigError | ConnectionLost)
    text = str(e.value)
    assert "\n" not in text and all(w in text for w in words), text


def test_socketcan_on_this_kernel():
    """A vcan/socketcan test needs a kernel with SocketCAN; where there is none (this build machine: AF_CAN is not
    supported) the error line says so and names what is needed."""
    if _has_socketcan():
        with pytest.raises(StationError, match="can9") as e:  # a SocketCAN kernel without that interface
            open_robot(f"canopen+socketcan://can9?{Q}")
    else:
        with pytest.raises(ConfigError, match="no SocketCAN.*can-raw") as e:
            open_robot(f"canopen+socketcan://can0?{Q}")
    assert "\n" not in str(e.value)


def test_the_station_command_prints_one_line_and_exits_2(tmp_path):
    env = {**os.environ, "STATION_HOME": str(tmp_path)}
    r = station_proc("run", "zero_offsets", "--robot", f"canopen+pcan://PCAN_USBBUS1?{Q}", "--serial", "X", env=env)
    assert r.code == 2, r.err
    lines = r.errors
    assert len(lines) == 1 and "canopen+pcan" in lines[0] and "PCAN-Basic" in lines[0], r.err
    assert "Traceback" not in r.err and r.err.count("\n") == 1, r.err


def test_bad_bitrate_is_refused():
    with pytest.raises(ConfigError, match="bitrate"):
        open_robot("canopen+pcan://PCAN_USBBUS1?nodes=1-6&model=arm6&bitrate=fast")


class StateBus(VirtualBus):
    """python-can's virtual bus with a bus state, as interfaces such as PCAN and IXXAT report one."""

    bus_state = can.BusState.ACTIVE

    @property
    def state(self) -> can.BusState:
        return StateBus.bus_state


def test_bus_off_from_python_cans_bus_state(monkeypatch):
    """Bus-off found through python-can's own bus state (ERROR), not only error frames: BusError, robot stopped."""
    import time
    import uuid

    from station.drivers.canopen import interfaces
    from station.mocks.canopen.emulator import CanopenEmulator
    from station.mocks.world import World

    from station.robot import BusError

    # registered as python-can's plugin interfaces are (its backend table), for this test only
    monkeypatch.setitem(can.interfaces.BACKENDS, "statebus", (__name__, "StateBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"statebus"})
    monkeypatch.setitem(interfaces.INTERFACES, "statebus", ("virtual bus with a state", "nothing"))
    monkeypatch.setattr(StateBus, "bus_state", can.BusState.ACTIVE)
    chan = f"state-{uuid.uuid4().hex[:8]}"
    with CanopenEmulator(World.default(model="arm6", seed=3), channel=chan):
        robot = CanopenRobot(load_model("arm6"), list(range(1, 7)), interface="statebus", channel=chan)
        try:
            robot.joint_positions()
            StateBus.bus_state = can.BusState.ERROR
            end = time.monotonic() + 1.0
            with pytest.raises(BusError, match="bus-off.*bus state ERROR"):
                while time.monotonic() < end:
                    robot.joint_positions()
                    time.sleep(0.01)
        finally:
            StateBus.bus_state = can.BusState.ACTIVE
            robot.close()
