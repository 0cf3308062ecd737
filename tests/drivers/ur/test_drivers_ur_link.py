"""The UR driver's link, power-up, safety words and jog watchdog (``station.drivers.ur.link``, ``power``,
``safety``, ``watchdog``) against the UR controller emulator in its own process, which boots with the arm powered
off as a controller does. Robot modes and safety status bits as the RTDE guide numbers them."""

from __future__ import annotations

import time

import pytest
from station.drivers.ur.dashboard import DashboardClient
from station.drivers.ur.link import RTDELink
from station.drivers.ur.power import power_up
from station.drivers.ur.safety import ROBOT_MODE_POWER_OFF, ROBOT_MODE_RUNNING, mode_name, safety_error
from station.drivers.ur.watchdog import JogWatchdog

from station.robot import open_robot
from station.robot.errors import ConfigError, ConnectionLost, SafetyStop


def test_safety_bits_and_modes_as_the_rtde_guide_numbers_them():
    # safety_status_bits: 2 protective stopped, 4 safeguard stopped, 5..7 emergency stopped, 8 violation, 9 fault
    assert safety_error("h", 0b1) is None  # bit 0: normal mode
    assert "protective stop" in str(safety_error("h", 1 << 2)) and "safeguard" in str(safety_error("h", 1 << 4))
    for bit in (5, 6, 7):
        err = safety_error("h", 1 << bit)
        assert isinstance(err, SafetyStop) and "emergency stop" in str(err)
    assert "fault/violation" in str(safety_error("h", 1 << 9)) and str(safety_error("h", 1 << 8)).startswith("ur://h")
    assert (mode_name(3), mode_name(5), mode_name(7), mode_name(42)) == ("POWER_OFF", "IDLE", "RUNNING", "42")


def test_link_power_up_and_the_lost_link(emulators):
    emu = emulators("ur", model="ur5e")
    link = RTDELink(emu.host, DashboardClient(emu.host), stale_timeout=2.0)
    link.open_receive()
    try:
        link.check()
        assert int(link.receive.getRobotMode()) == ROBOT_MODE_POWER_OFF  # a controller boots powered off
        with pytest.raises(ConfigError, match="add power_on=yes to the robot URL"):
            power_up(link, False, lambda: None)
        power_up(link, True, lambda: None)  # power on, brake release, as the dashboard does it
        assert int(link.receive.getRobotMode()) == ROBOT_MODE_RUNNING
        assert "RUNNING" in link.dashboard.command("robotmode")
        emu.close()  # the controller goes away
        end = time.monotonic() + 10
        with pytest.raises(ConnectionLost, match="connection to the controller lost"):
            while time.monotonic() < end:
                link.check()
                time.sleep(0.05)
        assert link.lost
    finally:
        link.drop()


def test_the_jog_watchdog_is_armed_by_a_velocity_jog_and_stays_until_the_script_ends(emulators):
    emu = emulators("ur", model="ur5e")
    with open_robot(emu.url + "&power_on=yes") as robot:
        robot.enable()
        dog: JogWatchdog = robot._watchdog
        assert not dog.armed and dog.diagnosis() == ""
        robot.jog_velocity("joint", 5, 0.05)
        time.sleep(0.1)
        assert dog.armed and dog.hz > 0 and "RTDE watchdog" in dog.diagnosis()
        robot.stop()
        assert dog.armed and not dog.ended_script(time.monotonic())  # the program still runs


def test_ctrl_c_anywhere_in_a_bounded_wait_sets_the_running_interface_aside(emulators, monkeypatch):
    """Ctrl-C that lands in the stall check beside the 20 ms wait (not in the wait itself) still abandons the
    control interface whose call runs on: the teardown must not disconnect it under that call (ur_rtde crashed
    there once in CI). The interface here is a stand-in whose command never returns in time."""
    import station.drivers.ur.link as link_module

    emu = emulators("ur", model="ur5e")
    link = RTDELink(emu.host, DashboardClient(emu.host), stale_timeout=5.0)

    class Hanging:  # the command is still inside the call when Ctrl-C comes
        def moveJ(self, *args):  # noqa: N802 (ur_rtde's name)
            time.sleep(1.0)
            return True

    hanging = Hanging()
    link.control = hanging

    class Interrupted(link_module.Silence):
        def tick(self) -> float:
            raise KeyboardInterrupt

    monkeypatch.setattr(link_module, "Silence", Interrupted)
    try:
        with pytest.raises(KeyboardInterrupt):
            link.bounded("moveJ", hanging.moveJ)
        assert link.control is None and link.abandoned is hanging
    finally:
        link.abandoned = None
        link.drop()
