"""Every CAN adapter python-can speaks, under one URL form: ``canopen+<interface>://<channel>?bitrate=...``.

python-can's own configuration underneath (``can.Bus(interface=..., channel=..., bitrate=...)``: its config file
and environment fill what the URL leaves out). A missing interface library or absent hardware is one line naming
the interface and what to install (pip package, vendor driver), raised as a station error (exit 2)."""

from __future__ import annotations

import socket

from station.robot.errors import ConfigError, ConnectionLost
from station.robot.registry import bus_library

with bus_library("python-can"):
    import can

# interface -> (what it is, what it needs besides python-can)
INTERFACES = {
    "socketcan": ("Linux SocketCAN", "a Linux kernel with the can and can-raw modules and the interface up "
                  "(ip link set CHANNEL up type can bitrate 500000); no pip package beyond python-can"),
    "pcan": ("PEAK PCAN", "PEAK's PCAN-Basic library (libpcanbasic on Linux, PCANBasic.dll on Windows) from "
             "the PEAK driver package; pip: python-can (uptime optional)"),
    "kvaser": ("Kvaser CANlib", "Kvaser's CANlib (Linux: the linuxcan driver with libcanlib; Windows: Kvaser "
               "Drivers for Windows); pip: python-can"),
    "ixxat": ("HMS IXXAT VCI", "the HMS IXXAT VCI driver (Windows VCI 4; on Linux use the IXXAT SocketCAN driver "
              "and canopen+socketcan); pip: python-can"),
    "slcan": ("serial-line CAN (slcan)", "pip: pyserial (python-can[serial]) and the adapter's serial port"),
    "virtual": ("python-can virtual bus", "nothing (same process only)"),
    "socketcand": ("socketcand", "a socketcand daemon serving the bus (socketcand -i can0 -l lo)"),
}
SCHEMES = tuple(f"canopen+{name}" for name in INTERFACES)


def _missing_library(e: BaseException) -> bool:
    """python-can's ways of saying an interface's library is not there (4.x): ImportError, its
    CanInterfaceNotImplementedError, a NameError from kvaser's module without CANlib, pcan's OSError."""
    if isinstance(e, ImportError | can.CanInterfaceNotImplementedError | NameError):
        return True
    text = str(e).lower()
    return isinstance(e, OSError) and ("library" in text or "dll" in text or "not found" in text)


def open_can(interface: str, channel: str, *, host: str | None = None, port: int | None = None,
             bitrate: int | None = None, where: str = "") -> can.BusABC:
    if interface not in INTERFACES:
        raise ConfigError(f"canopen: interface {interface!r} is not one of {', '.join(INTERFACES)}")
    what, needs = INTERFACES[interface]
    where = where or f"{interface} {channel}"
    kwargs = {} if bitrate is None else {"bitrate": bitrate}
    try:
        if interface == "socketcand":
            # python-can retries a refused connect for 10 s; probe first for a prompt, clear error
            with socket.create_connection((host, port), timeout=2.0):
                pass
            return can.Bus(interface="socketcand", host=host, port=port, channel=channel, tcp_tune=True)
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except BaseException as e:  # noqa: BLE001 - every backend error becomes one line naming what to install
        if isinstance(e, KeyboardInterrupt | SystemExit):
            raise
        detail = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if isinstance(e, NameError):  # python-can's kvaser module after "Kvaser canlib is unavailable"
            detail = "the library did not load"
        if _missing_library(e):
            raise ConfigError(f"canopen+{interface}: the {what} interface cannot load its library ({detail}); "
                              f"it needs {needs}") from None
        if interface == "socketcan" and isinstance(e, OSError) and e.errno == 97:
            raise ConfigError(f"canopen+socketcan: this kernel has no SocketCAN ({detail}); it needs {needs}") from None
        raise ConnectionLost(f"cannot open CAN bus {where}: {detail} (the {what} interface needs {needs})") from None
