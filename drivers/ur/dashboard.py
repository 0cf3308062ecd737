"""Minimal client for the UR dashboard server (TCP 29999, one text line per command and per reply).

The ur-rtde Python wheel does not expose its C++ DashboardClient, so the driver speaks the line protocol
itself: status, serial number, unlock of a protective stop, program stop, power (``power on`` and ``brake
release`` are sent by the driver's ``_power_up`` one at a time, each after the robot mode it needs)."""

from __future__ import annotations

import contextlib
import socket

from station.robot.errors import BusError, ConnectionLost

DASHBOARD_PORT = 29999


class DashboardClient:
    def __init__(self, host: str, port: int = DASHBOARD_PORT, timeout: float = 2.5) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self._sock: socket.socket | None = None
        self._file = None
        self.banner = ""

    def connect(self) -> None:
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
            self._file = self._sock.makefile("rb")
            self.banner = self._readline()
        except OSError as e:
            self.close()
            raise ConnectionLost(f"ur://{self.host}: dashboard server {self.host}:{self.port} not reachable "
                                 f"({e})") from None

    def _readline(self) -> str:
        line = self._file.readline()
        if not line:
            raise ConnectionLost(f"ur://{self.host}: dashboard server closed the connection")
        return line.decode("utf-8", "replace").strip()

    def command(self, text: str) -> str:
        if self._sock is None:
            self.connect()
        try:
            self._sock.sendall((text + "\n").encode())
            return self._readline()
        except TimeoutError:
            self.close()
            raise BusError(f"ur://{self.host}: dashboard command {text!r} got no answer in {self.timeout} s") \
                from None
        except OSError as e:
            self.close()
            raise ConnectionLost(f"ur://{self.host}: dashboard connection lost during {text!r} ({e})") from None

    def close(self) -> None:
        for thing in (self._file, self._sock):
            if thing is not None:
                with contextlib.suppress(OSError):
                    thing.close()
        self._sock = self._file = None

    # ---- commands the driver uses ------------------------------------------------------------
    def polyscope_version(self) -> str:
        return self.command("PolyscopeVersion")

    def serial_number(self) -> str:
        return self.command("get serial number")

    def robot_model(self) -> str:
        return self.command("get robot model")

    def is_in_remote_control(self) -> bool:
        return "true" in self.command("is in remote control").lower()

    def safety_status(self) -> str:
        return self.command("safetystatus")

    def unlock_protective_stop(self) -> tuple[bool, str]:
        reply = self.command("unlock protective stop")
        return reply == "Protective stop releasing", reply

    def close_safety_popup(self) -> str:
        return self.command("close safety popup")

    def stop_program(self) -> str:
        return self.command("stop")

    def power_off(self) -> str:
        return self.command("power off")
