"""``station opcua``: the OPC UA server for the line alone, without the web page (docs/opcua.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from station.cli.run_options import CONE, DB, HOLDOUT, LIMITS, POSES, REFERENCE


def opcua(
    robot: str = typer.Option(..., "--robot", help="Robot URL."),
    cell: Path = typer.Option(..., "--cell", help="Cell file (reference points)."),
    endpoint: str = typer.Option("opc.tcp://127.0.0.1:4840", "--endpoint", help="OPC UA endpoint (loopback "
                                 "unless configured; off loopback Basic256Sha256 with --cert/--key and --users)."),
    procedure: str = typer.Option("zero_offsets", "--procedure", help="Default procedure of Start."),
    limits: Path = LIMITS,
    db: str = DB,
    reference: str = REFERENCE,
    poses: int = POSES,
    holdout: int = HOLDOUT,
    cone: str = CONE,
    cert: Path = typer.Option(None, "--cert", help="Server certificate for Basic256Sha256."),
    key: Path = typer.Option(None, "--key", help="Server private key (PEM) for Basic256Sha256."),
    trust: Path = typer.Option(None, "--trust", help="Folder of trusted client certificates."),
    users: Path = typer.Option(None, "--users", help="Users file: names, password hashes, rights read/operate "
                               "(required off loopback; docs/opcua.md)."),
) -> None:
    """OPC UA server: object Station (State, Serial, Procedure, Step, Progress, Verdict, LastResult;
    Start(serial, procedure) -> session, Abort())."""
    import asyncio

    from station.cli.panel_cmd import _check_files
    from station.cli.run_cmd import _options
    from station.opcua.server import OpcuaOptions, check_security, serve_forever
    from station.panel import Controller, PanelConfig

    opts = OpcuaOptions(endpoint, cert, key, trust, users=users)
    check_security(opts)
    cfg = PanelConfig(robot=robot, cell=str(cell), procedure=procedure, limits=str(limits) if limits else None,
                      db=db, options=_options(poses, holdout, cone, reference, None), confirm=False)
    _check_files(cfg)
    ctl = Controller(cfg)
    typer.echo(f"station: OPC UA at {endpoint} (namespace urn:station)", err=True)
    try:
        asyncio.run(serve_forever(ctl, opts))
    finally:
        if ctl.busy:
            ctl.abort()
            ctl.join(30)


def register(app: typer.Typer) -> None:
    app.command("opcua")(opcua)
