"""``station jog``: the technician's terminal UI (see docs/jog.md)."""

from __future__ import annotations

import signal
from pathlib import Path
from urllib.parse import parse_qs, urlencode, urlsplit, urlunsplit

import typer


def url_with_model(url: str, model: str | None) -> str:
    """Put ``--model`` into the robot URL's query (the drivers read ``model=`` there)."""
    if not model:
        return url
    parts = urlsplit(url)
    query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
    query["model"] = model
    return urlunsplit(parts._replace(query=urlencode(query, safe=",-/:")))


def ask_serial(reported: str | None) -> str:
    """The technician confirms the serial the session is filed under (Enter takes the one the robot or the URL
    reports, if any). Never asked without a terminal: then ``--serial`` is required."""
    import sys

    from station.robot.errors import ConfigError

    if not sys.stdin.isatty():
        raise ConfigError("--serial is required: the session is filed under the robot's serial, and there is no "
                          "terminal to confirm it on")
    hint = f"the robot reports {reported}: Enter confirms it" if reported else "the robot reports none"
    for _ in range(3):
        answer = typer.prompt(f"robot serial for this jog session ({hint})", default=reported or "",
                              show_default=False).strip()
        if answer:
            return answer
    raise ConfigError("no serial confirmed: the session is filed under the robot's serial (--serial SN)")


def open_jog(url: str, *, serial: str | None = None, model: str | None = None, session: Path | None = None,
             identify: str = "offsets,tcp", reference: list[str] | str | None = None, cell: Path | None = None,
             limits: Path | None = None, judge: str = "jog", confirm_serial=None):
    """Connect, create the session (journal + samples.csv) and return ``(robot, controller)``.
    Bad ``--reference``, cell or limits files fail before the robot is opened; the robot is closed again when
    anything after connecting fails. ``judge``: the limits section (procedure name) that judges the session;
    a model without one ends the session with the verdict NO LIMITS.

    The session is filed under a serial the technician confirmed: ``serial`` (``--serial``, checked against
    the one the robot or the URL reports), else ``confirm_serial(reported)``, which is offered the serial the
    robot/URL reports but never one the driver made up from device ids. Neither: ConfigError."""
    from station.engine.cell import load_cell
    from station.engine.limits import load_limits
    from station.robot import adopt_serial, open_robot
    from station.robot.errors import ConfigError
    from station.robot.url import parse_url
    from station.tui.controller import JogController, parse_reference
    from station.tui.session import session_header, technician_session

    parse_url(url)  # a malformed URL is the same one-line error as for station run, before anything else
    ref = parse_reference(reference)
    the_cell = load_cell(cell) if cell is not None else None
    lim = load_limits(limits)
    full_url = url_with_model(url, model)
    robot = open_robot(full_url)
    try:
        robot.model.select(identify)  # unknown group: one-line error before anything is written
        ident = robot.identity()
        if not serial:
            reported = ident.serial if ident.serial and ident.serial_source != "derived" else None
            if confirm_serial is None:
                raise ConfigError("--serial is required: the session is filed under the robot's serial"
                                  + (f" (the robot reports {reported})" if reported else
                                     " (the robot reports none; device ids are no serial)"))
            serial = str(confirm_serial(reported))
        ident = adopt_serial(ident, serial)  # same rule as station run: the wrong robot fails here
        sn = serial
        header = session_header(identity=ident, model_name=robot.model.name, serial=sn, identify=identify,
                                reference=ref, url=full_url)
        header.limits = {"path": lim.path, "version": lim.version, "sha256": lim.sha256, "procedure": judge}
        if the_cell is not None:
            from station.kinematics.collision import keep_out_to_doc

            header.cell = {"path": the_cell.path, "model": the_cell.model, "tool": the_cell.tool,
                           "points": [p.to_dict() for p in the_cell.points.values()],
                           **keep_out_to_doc(the_cell.keep_out)}
        sid = session.name if session is not None else None
        jog_session = technician_session(robot, header, folder=session, session_id=sid)
        try:
            table = lim.for_procedure(robot.model.name, judge)
        except ConfigError:
            table = {}  # nothing to judge against: the session ends with NO LIMITS
        ctl = JogController(robot, jog_session, identify=identify, reference=ref, cell=the_cell, limits=table,
                            limits_version=lim.version, judged_as=judge)
    except BaseException:
        robot.close()
        raise
    return robot, ctl


def store_in_records(folder: Path, db: str | None) -> bool:
    """Project the journal into the records database. A failure is reported, not fatal: the session folder
    (journal + samples.csv) is complete and can be stored again later. A session without a kept sample is
    not stored (nothing to file under the robot's history; its journal stays in the folder)."""
    from station.engine.session_record import session_from_journal
    from station.publish import store_record

    try:
        record = session_from_journal(folder)
        if not record.get("samples"):
            typer.echo("no samples kept: the session is not stored in the records database", err=True)
            return False
        store_record(record, db)
    except Exception as e:  # any database/driver error: the journal is the truth, say so and go on
        typer.echo(f"station: warning: session not stored in the records database: {e}", err=True)
        return False
    return True


def register(app: typer.Typer) -> None:
    @app.command("jog")
    def jog(
        robot: str = typer.Option(..., "--robot", help="robot URL, e.g. canopen+socketcand://127.0.0.1:29536"
                                                      "?channel=can0&nodes=1-6&model=arm6"),
        serial: str = typer.Option(None, "--serial", help="robot serial for the session (default: as the robot "
                                                         "reports it)"),
        model: str = typer.Option(None, "--model", help="kinematic model name or file (default: from the URL)"),
        session: Path = typer.Option(None, "--session", help="session folder (default: "
                                                            "$STATION_HOME/sessions/<id>/)"),
        identify: str = typer.Option("offsets,tcp", "--identify", help="parameters for the live solve"),
        reference: list[str] = typer.Option(None, "--reference",
                                            help="unknown | x,y,z (point A; m, or suffix mm) | LABEL=x,y,z "
                                                 "(repeatable), as for station solve"),
        db: str = typer.Option(None, "--db", help="records database URL (default $STATION_DB, else "
                                                  "sqlite:///$STATION_HOME/station.db)"),
        cell: Path = typer.Option(None, "--cell", help="cell file (station-cell/1): its points are offered in "
                                                      "order and its keep-out checks every jog target"),
        limits: Path = typer.Option(None, "--limits", help="limits file (default: the shipped limits.yaml)"),
        judge: str = typer.Option("jog", "--judge", help="limits section (procedure name) that judges the "
                                                         "session, e.g. zero_offsets; none for the model: NO LIMITS"),
    ) -> None:
        """Jog the robot, touch reference points, record samples, watch the live solve, write back."""
        # db: stored after the UI closes; the journal in the session folder stays the truth either way
        from station.solver import SolverInputError
        from station.tui.app import JogApp

        try:
            rob, ctl = open_jog(robot, serial=serial, model=model, session=session, identify=identify,
                                reference=reference, cell=cell, limits=limits, judge=judge,
                                confirm_serial=ask_serial)
        except (KeyError, SolverInputError) as e:
            typer.echo(f"station: error: --identify {identify!r}: {e.args[0] if e.args else e}", err=True)
            raise typer.Exit(2) from None
        app = JogApp(ctl)
        try:
            app.run()
        finally:
            ctl.close()
            rob.close()
        kept = ctl.session.samples()
        if not kept:  # nothing to judge, store or solve: say only that (the journal stays in the folder)
            typer.echo(f"no samples kept: the session is not stored in the records database; its journal stays in "
                       f"{ctl.session.folder}")
        else:
            store_in_records(ctl.session.folder, db)
            forced = ctl.solve_state.forced
            typer.echo(f"session saved: {ctl.session.folder}\n"
                       f"  verdict: {ctl.verdict_text or 'none'} (limits: {ctl.judged_as} for {rob.model.name}"
                       f"{'' if ctl.limits else ', none defined'})\n"
                       + (f"  {forced} of {len(kept)} samples forced (recorded without contact): no calibration "
                          "from them\n" if forced else "")
                       + f"  solve it: {ctl.solve_command()}")
        if app.interrupted is not None:  # SIGTERM/SIGINT: quit cleanly as ctrl+q does, exit status 130
            typer.echo(f"station: interrupted ({signal.Signals(app.interrupted).name}); robot stopped, session "
                       "saved", err=True)
            raise typer.Exit(130)
