"""The jog watchdog: the control script's RTDE watchdog on the command register (ur_rtde's ``setWatchdog``, which
the script turns into ``rtde_set_watchdog(..., "stop")``), as the driver keeps it.

Armed for speed jogs, it makes the controller itself stop the program when the station or the network stops
writing the register, so a dead station cannot leave the arm running. It stays armed for the script's lifetime:
every speed command and every kick is a write it counts; between jogs the standing arm is kept at the slower
JOG_IDLE_WATCHDOG_HZ. Anything that is not followed by kicks (freedrive, unwatched moves) ends the script that
carries it first (``disarm``).

Units: Hz (rates), seconds (``time.monotonic`` instants)."""

from __future__ import annotations

import time
from collections.abc import Callable

from station.drivers.ur.link import RTDELink

JOG_IDLE_WATCHDOG_HZ = 1.0  # the RTDE watchdog between velocity jogs (arm standing; jog_keep_alive feeds it)
# a waited move_joints carries it too: ur_rtde's script runs a moveJ to its end without its client, so a station
# killed mid-move stops the arm within 0.5 s; once the arm stands it is relaxed (1000 s: a seat, a technician's
# freedrive), not ended: an expiry only means a fresh script for the next command, and a script start per move
# was slow on a busy PC
MOVE_WATCHDOG_HZ = 2.0
MOVE_IDLE_WATCHDOG_HZ = 0.001


class JogWatchdog:
    """What the running control script's watchdog is (``hz``, 0: none) and when we last wrote the register it
    watches (``last_write``). ``bounded(what, fn, *args)`` runs a command that waits for the controller (the
    robot's, so the RTDE stall timeout applies)."""

    def __init__(self, link: RTDELink, bounded: Callable) -> None:
        self._link = link
        self._bounded = bounded
        self.hz = 0.0
        self.speed_sent = 0.0  # monotonic: our last speed command
        self.last_kick = 0.0
        self.last_write = 0.0  # monotonic: our last write to the command register (what the watchdog watches)

    @property
    def armed(self) -> bool:
        return self.hz > 0

    def script_started(self) -> None:
        """A new control script carries no watchdog."""
        self.hz = 0.0

    # A write is dated when it is sent, not when the command returns: the controller counts the watchdog from
    # receiving it, which is before ur_rtde's command returns (it waits for the script to take the command).
    # Dated at the return, a loaded station saw the watchdog's stop come "too early" and called it someone
    # else's stop (CI, "the control script stopped during the jog (not by the station)").
    def wrote(self, sent: float | None = None) -> None:
        self.last_write = time.monotonic() if sent is None else sent

    def speed_written(self, sent: float | None = None) -> None:
        # kicks wait for the script to read the command (from the command's return)
        self.speed_sent = time.monotonic()
        self.last_write = self.speed_sent if sent is None else sent

    def kick(self) -> None:
        # A kick writes 0 into the command register: never within a few controller cycles of a speed
        # command, or the script would not have read the command yet (and the jog would never start).
        now = time.monotonic()
        if self.armed and now - self.speed_sent > 0.01 and now - self.last_kick > 0.02:
            self._link.control.kickWatchdog()
            self.last_kick = self.last_write = now

    def arm(self, hz: float) -> None:
        """The script's rtde_set_watchdog on the command register at ``hz`` (``"stop"``: a station or network
        that stops writing stops the program); it stays armed until the script ends. No-op when already at hz."""
        if hz <= 0 or self.hz == hz:
            return
        sent = time.monotonic()
        if self._bounded("setWatchdog", self._link.control.setWatchdog, hz):
            self.hz = hz
            self.last_write = sent
        # refused: the script is gone (a new one starts without a watchdog: URRobot._ready_for_motion). What it
        # carried and our last write are kept, so the next command can tell whether that watchdog ended it.

    def disarm(self) -> None:
        """Before anything that is not followed by kicks (freedrive, unwatched moves): end the script that
        carries the jog watchdog; a fresh one (without it) is uploaded by URRobot._ready_for_motion. The relaxed
        watchdog a waited move leaves (1000 s) is kept: ending the script and starting a fresh one before every
        seat timed out now and then."""
        if self.armed and self.hz != MOVE_IDLE_WATCHDOG_HZ:
            self._link.check()
            if self._link.control.isProgramRunning():
                self._link.control.stopScript()
            self.hz = 0.0

    def to_idle(self) -> None:
        """After a velocity jog's speedStop: the arm stands, so the armed watchdog may wait longer
        (JOG_IDLE_WATCHDOG_HZ) for the keep-alive until the next jog sets ``jog_watchdog`` again before its
        first speed command. At 10 Hz a keep-alive late by 0.1 s (a busy station PC) ended the program, and
        the next press had to upload the script first (or met the program ending under its speed command)."""
        if self.armed and self.hz > JOG_IDLE_WATCHDOG_HZ:
            self.arm(JOG_IDLE_WATCHDOG_HZ)

    def ended_script(self, previous_write: float) -> bool:
        """The script is gone and the jog watchdog can be what ended it: armed, and nothing written for at least
        its period (the controller counts from receiving our write, which is later than sending it). Anything
        else that ends the script (Stop on the pendant, a script error) is never resumed by the driver."""
        return (not self._link.control.isProgramRunning() and self.armed
                and time.monotonic() - previous_write >= 1.0 / self.hz)

    def diagnosis(self) -> str:
        """For a refused command: the controller ends the program when its RTDE watchdog starves (PolyScope's log
        says so; RTDE does not), so say whether one was armed and how long ago we last wrote."""
        if not self.armed:
            return ""
        return (f"; its RTDE watchdog ({self.hz:g} Hz) was armed, last write "
                f"{(time.monotonic() - self.last_write) * 1e3:.0f} ms before")
