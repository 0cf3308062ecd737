"""Bringing a UR arm to RUNNING, the way UR's own ROS driver does it (``robot_state_helper``): dashboard
``power on``, wait for IDLE (joints booted, brakes engaged), ``brake release``, wait for RUNNING. Only where
the robot URL allows it (``power_on=yes``); otherwise refused in one line naming the option.

Units: seconds. The waits count only time this process observed (``Silence``): a loaded station PC's own
scheduling gaps are not the controller's slowness."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from station.drivers.ur.link import RTDELink
from station.drivers.ur.safety import (
    ROBOT_MODE_BOOTING,
    ROBOT_MODE_IDLE,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_POWER_ON,
    ROBOT_MODE_RUNNING,
    mode_name,
    safety_error,
)

from station.robot.errors import ConfigError, DeviceFault
from station.robot.silence import Silence

log = logging.getLogger("station.drivers.ur")

# power on -> IDLE and brake release -> RUNNING: UR's client library waits up to 300 s / 30 s (counted in polls)
POWER_ON_TIMEOUT_S, BRAKE_RELEASE_TIMEOUT_S = 60.0, 30.0


def power_up(link: RTDELink, allowed: bool, check_safety: Callable[[], None]) -> None:
    """The arm RUNNING, or one line saying why not. ``allowed``: the URL's ``power_on=yes``; ``check_safety``
    raises (robot stopped) on a safety stop, which no power-up may step over."""
    host, receive, dash = link.host, link.receive, link.dashboard
    mode = int(receive.getRobotMode())
    if mode == ROBOT_MODE_RUNNING:
        return
    check_safety()
    if not allowed:
        raise ConfigError(f"ur://{host}: the arm is not running (dashboard: "
                          f"{dash.command('robotmode')}); power it on and release the brakes on the teach "
                          "pendant, or let the station do it: add power_on=yes to the robot URL")
    if mode in (ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_BOOTING):
        if mode == ROBOT_MODE_POWER_OFF:
            log.info("ur://%s: power on (power_on=yes)", host)
            dash.command("power on")
        mode = _wait_mode(link, (ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING), POWER_ON_TIMEOUT_S, "power-on",
                          "IDLE after 'power on'")
    if mode == ROBOT_MODE_IDLE:
        log.info("ur://%s: brake release (power_on=yes)", host)
        dash.command("brake release")
        mode = _wait_mode(link, (ROBOT_MODE_RUNNING,), BRAKE_RELEASE_TIMEOUT_S, "brake-release",
                          "RUNNING after 'brake release'")
    if mode != ROBOT_MODE_RUNNING:
        raise DeviceFault(f"ur://{host}: the arm is in robot mode {mode_name(mode)}, which needs the "
                          "teach pendant (confirm safety, release the teach button); nothing was moved")


def _wait_mode(link: RTDELink, targets: tuple[int, ...], timeout: float, which: str, what: str) -> int:
    silence = Silence()  # the station's own scheduling gaps are not the controller's slowness
    while True:
        link.check()
        mode = int(link.receive.getRobotMode())
        if mode in targets:
            return mode
        bits = int(link.receive.getSafetyStatusBits())
        err = safety_error(link.host, bits)
        if err is not None:
            raise err
        if silence.tick() > timeout:
            raise DeviceFault(f"ur://{link.host}: {which} timeout: the arm did not reach {what} within "
                              f"{timeout:g} s (robot mode {mode_name(mode)}; {silence.note()})")
        time.sleep(0.02)
