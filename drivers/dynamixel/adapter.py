"""The USB adapter under the bus: its FTDI latency timer.

An FTDI USB-serial chip (ROBOTIS U2D2, USB2Dynamixel) holds received bytes up to its latency timer before it sends
them to the host; Linux exposes it as ``/sys/bus/usb-serial/devices/ttyUSBn/latency_timer`` (ms, default 16).
ROBOTIS recommend 1 ms (e-Manual, DYNAMIXEL Wizard 2.0 "USB latency setting"; the "FastSyncRead Rx Fail" reports
in ROBOTIS-GIT/dynamixel_hardware_interface issues 79 and 83 were fixed by it): at 16 ms every answer waits up to
16 ms in the adapter. A pty (the emulator) or a non-FTDI adapter has no such file: the timer is unknown."""

from __future__ import annotations

import os
from pathlib import Path

SYSFS = "/sys"
LATENCY_WARN_MS = 2  # above this the station says so (one line)


def latency_timer_ms(port: str, sysfs_root: str | os.PathLike = SYSFS) -> int | None:
    """The adapter's latency timer (ms) for serial port ``port`` (a /dev path or a symlink to it, such as
    /dev/serial/by-id/...), or None when the system has none for it (a pty, a non-FTDI adapter, no sysfs)."""
    try:
        name = Path(os.path.realpath(port)).name
    except (OSError, ValueError):
        return None
    path = Path(sysfs_root) / "bus" / "usb-serial" / "devices" / name / "latency_timer"
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def latency_warning(port: str, timer_ms: int | None) -> str | None:
    """One line when the timer is known and above LATENCY_WARN_MS, else None."""
    if timer_ms is None or timer_ms <= LATENCY_WARN_MS:
        return None
    name = Path(os.path.realpath(port)).name
    return (f"dynamixel: {port}: the USB adapter's latency timer is {timer_ms} ms (FTDI default 16); every answer "
            f"waits that long in the adapter: set 1 ms as ROBOTIS recommend "
            f"(echo 1 | sudo tee /sys/bus/usb-serial/devices/{name}/latency_timer, or a udev rule)")
