"""Listen: loopback unless configured, and off loopback never without authentication (a bearer token or TLS
client certificates)."""

from __future__ import annotations

import ipaddress
import socket
import sys
from dataclasses import dataclass
from pathlib import Path


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


@dataclass(frozen=True)
class TLS:
    """HTTPS for the panel: the server's certificate and key; with ``client_ca`` every client must show a
    certificate that CA signed (TLS client authentication)."""

    cert: Path
    key: Path
    client_ca: Path | None = None


def check_listen(host: str, token: str | None, tls: TLS | None = None) -> None:
    """Refuse (one line) to listen off loopback without a bearer token or TLS client authentication, and TLS
    files that are not there."""
    from station.robot.errors import ConfigError

    if tls is not None:
        for opt, p in (("--tls-cert", tls.cert), ("--tls-key", tls.key), ("--tls-client-ca", tls.client_ca)):
            if p is not None and not Path(p).is_file():
                raise ConfigError(f"{opt} {p}: no such file")
        import ssl

        try:
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ctx.load_cert_chain(str(tls.cert), str(tls.key))
            if tls.client_ca is not None:
                ctx.load_verify_locations(str(tls.client_ca))
        except (ssl.SSLError, OSError, ValueError) as e:
            raise ConfigError(f"TLS files {tls.cert}, {tls.key}: {' '.join(str(e).split()) or type(e).__name__}") \
                from None
    if not is_loopback(host) and not token and (tls is None or tls.client_ca is None):
        raise ConfigError(f"--host {host} is not loopback: the panel then requires --token (or "
                          "$STATION_PANEL_TOKEN) or TLS client certificates (--tls-cert, --tls-key, --tls-client-ca) "
                          "so that only the line's clients can start a unit")
    if not is_loopback(host) and token and tls is None:
        print("station: warning: the bearer token crosses the network in clear text; give --tls-cert/--tls-key "
              "(or put a TLS reverse proxy in front, docs/panel.md)", file=sys.stderr, flush=True)


def serve(app, host: str, port: int, tls: TLS | None = None) -> None:
    """Run the app until Ctrl-C (uvicorn)."""
    import ssl

    import uvicorn

    kw = {}
    if tls is not None:
        kw = {"ssl_certfile": str(tls.cert), "ssl_keyfile": str(tls.key)}
        if tls.client_ca is not None:
            kw |= {"ssl_ca_certs": str(tls.client_ca), "ssl_cert_reqs": ssl.CERT_REQUIRED}
    uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False,
                                  # the guard checks Host itself; uvicorn must not trust forwarded headers
                                  proxy_headers=False, server_header=False,
                                  # open event streams (pages) must not hold a Ctrl-C up
                                  timeout_graceful_shutdown=2, **kw)).run()
