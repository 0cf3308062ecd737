"""Listen: loopback unless configured, and never without a token off loopback."""

from __future__ import annotations

import ipaddress
import socket


def is_loopback(host: str) -> bool:
    if host in ("localhost", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        try:
            return all(ipaddress.ip_address(a[4][0]).is_loopback for a in socket.getaddrinfo(host, None))
        except OSError:
            return False


def check_listen(host: str, token: str | None) -> None:
    from station.robot.errors import ConfigError

    if not is_loopback(host) and not token:
        raise ConfigError(f"--host {host} is not loopback: the panel then requires --token (or "
                          "$STATION_PANEL_TOKEN) so that only the line's clients can start a unit")


def serve(app, host: str, port: int) -> None:
    """Run the app until Ctrl-C (uvicorn)."""
    import uvicorn

    uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False,
                                # open event streams (pages) must not hold a Ctrl-C up
                                timeout_graceful_shutdown=2)).run()
