"""``station panel``: the operator panel in the browser (docs/panel.md), optionally with the OPC UA server for
the line (docs/opcua.md)."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from station.cli.run_options import CONE, DB, HOLDOUT, LIMITS, POSES, REFERENCE, TOUCH


def panel(
    robot: str = typer.Option(..., "--robot", help="Robot URL, e.g. dynamixel:///dev/ttyUSB0?model=omx"),
    cell: Path = typer.Option(..., "--cell", help="Cell file (reference points)."),
    procedure: str = typer.Option("zero_offsets", "--procedure", help="Procedure every unit runs."),
    host: str = typer.Option("127.0.0.1", "--host", help="Listen address (loopback unless configured)."),
    port: int = typer.Option(8470, "--port", help="TCP port of the page and API."),
    token: str = typer.Option(None, "--token", help="Bearer token; required off loopback (or "
                              "$STATION_PANEL_TOKEN)."),
    limits: Path = LIMITS,
    db: str = DB,
    touch: str = TOUCH,
    reference: str = REFERENCE,
    poses: int = POSES,
    holdout: int = HOLDOUT,
    cone: str = CONE,
    confirm: bool = typer.Option(True, "--confirm/--no-confirm", help="Ask the operator to confirm the unit is "
                                 "clamped before the robot moves."),
    opcua: str = typer.Option(None, "--opcua", help="Also serve OPC UA at this endpoint, e.g. "
                              "opc.tcp://127.0.0.1:4840."),
    opcua_cert: Path = typer.Option(None, "--opcua-cert", help="Server certificate (DER/PEM) for Basic256Sha256."),
    opcua_key: Path = typer.Option(None, "--opcua-key", help="Server private key (PEM) for Basic256Sha256."),
    opcua_trust: Path = typer.Option(None, "--opcua-trust", help="Folder of trusted client certificates."),
    opcua_users: Path = typer.Option(None, "--opcua-users", help="OPC UA users file (names, password hashes, "
                                     "rights read/operate); required off loopback."),
    tls_cert: Path = typer.Option(None, "--tls-cert", help="HTTPS: the panel's certificate (PEM)."),
    tls_key: Path = typer.Option(None, "--tls-key", help="HTTPS: the panel's private key (PEM)."),
    tls_client_ca: Path = typer.Option(None, "--tls-client-ca", help="HTTPS with client certificates: the CA "
                                       "(PEM) that signed them; every client must show one."),
    allow_host: list[str] = typer.Option(None, "--allow-host", help="Another name clients reach the panel by "
                                         "(e.g. a TLS reverse proxy's), NAME[:PORT]; repeatable."),
) -> None:
    """Operator panel: sign in, scan the serial, START, live progress, full-screen PASS/FAIL, history."""
    from station.cli.run_cmd import _options
    from station.panel import Controller, PanelConfig
    from station.panel.app import create_app
    from station.panel.serve import TLS, check_listen, is_loopback, serve
    from station.robot.errors import ConfigError

    token = token or os.environ.get("STATION_PANEL_TOKEN") or None
    if (tls_cert is None) != (tls_key is None) or (tls_client_ca is not None and tls_cert is None):
        raise ConfigError("HTTPS needs --tls-cert and --tls-key (and --tls-client-ca only with them)")
    tls = TLS(tls_cert, tls_key, tls_client_ca) if tls_cert is not None else None
    check_listen(host, token, tls)
    if touch is not None:  # read by its declaration, as station run does: a bad value never reaches a unit
        from station.engine.declare import TOUCH as TOUCH_OPTION

        TOUCH_OPTION.read(touch)
    cfg = PanelConfig(robot=robot, cell=str(cell), procedure=procedure, limits=str(limits) if limits else None,
                      db=db, options=_options(poses, holdout, cone, reference, None), touch=touch, confirm=confirm)
    _check_files(cfg)
    ctl = Controller(cfg)
    app = create_app(ctl, token, host=host, port=port, loopback=is_loopback(host), tls=tls is not None,
                     allow_hosts=tuple(allow_host or ()))  # a bad --allow-host: refused before anything starts
    bridge = None
    if opcua:
        from station.opcua.server import OpcuaOptions, start_in_thread

        bridge = start_in_thread(ctl, OpcuaOptions(opcua, opcua_cert, opcua_key, opcua_trust, users=opcua_users))
        typer.echo(f"station: OPC UA at {opcua} (namespace urn:station)", err=True)
    scheme = "https" if tls is not None else "http"
    typer.echo(f"station: panel at {scheme}://{host}:{port}/" + ("  (token required)" if token else "")
               + ("  (client certificates required)" if tls is not None and tls.client_ca else ""), err=True)
    try:
        serve(app, host, port, tls)
    finally:
        if ctl.busy:
            ctl.abort()
            ctl.join(30)
        if bridge is not None:
            bridge.stop()


def _check_files(cfg) -> None:
    """Bad cell/limits/procedure files fail now, with one line, not when the first unit is scanned."""
    from station.engine import load_procedure
    from station.engine.cell import load_cell
    from station.engine.limits import load_limits

    load_procedure(cfg.procedure)
    load_limits(cfg.limits)
    if cfg.cell:
        load_cell(cfg.cell)


def register(app: typer.Typer) -> None:
    app.command("panel")(panel)
