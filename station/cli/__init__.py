"""The ``station`` command. Each command group lives in its own module and registers itself here.

Errors the station raises on purpose (``StationError``, bad model files, bad input) print one line
``station: error: ...`` and exit 2; a traceback is a bug."""

from __future__ import annotations

import importlib
import sys

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Robot calibration station: jog, record, solve, verify, report, write back.")

# module -> it defines ``register(app: typer.Typer) -> None``
COMMAND_MODULES = (
    "station.cli.model_cmd",  # station model show|export|list
    "station.cli.solve_cmd",  # station solve, station fk
    "station.cli.mock_cmd",  # station mock dynamixel|canopen|ur|world
    "station.cli.run_cmd",  # station run, resume, demo
    "station.cli.jog_cmd",  # station jog
    "station.cli.records_cmd",  # station records list|show, report
    "station.cli.map_cmd",  # station map plan|build|apply|correct (seed 004 correction map)
    "station.cli.panel_cmd",  # station panel (operator page, optional OPC UA)
    "station.cli.opcua_cmd",  # station opcua (OPC UA server for the line)
)

for _name in COMMAND_MODULES:
    importlib.import_module(_name).register(app)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print the one-line error and return the exit to raise."""
    typer.echo(f"station: error: {message}", err=True)
    return typer.Exit(code)


def _quiet_bus_libraries() -> None:
    """Bus libraries log each failed transfer at ERROR; the typed error the station raises already says what
    happened in one line, so their narration is kept for ``STATION_DEBUG=1``."""
    import logging
    import os

    logging.basicConfig(level=logging.WARNING, format="station: %(name)s: %(message)s")
    debug = bool(os.environ.get("STATION_DEBUG"))
    for name in ("can", "canopen"):
        logging.getLogger(name).setLevel(logging.DEBUG if debug else logging.CRITICAL)


# the station's own one-line errors: module -> class
INPUT_ERRORS = {"station.robot.errors": "StationError", "station.kinematics.modelfile": "ModelFileError",
                "station.kinematics.parallel": "ParallelKinematicsError", "station.mocks.errors": "MockError"}


def _input_errors() -> tuple[type[BaseException], ...]:
    """The error classes of INPUT_ERRORS whose modules are imported: a class whose module was never imported
    cannot have been raised, and importing them up front would cost every command numpy and the kinematics."""
    return tuple(getattr(sys.modules[m], n) for m, n in INPUT_ERRORS.items() if m in sys.modules)


def main() -> None:
    _quiet_bus_libraries()
    try:
        # in non-standalone mode click *returns* the code of a raised Exit instead of exiting
        rc = app(standalone_mode=False)
        if isinstance(rc, int) and rc != 0:
            sys.exit(rc)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except _input_errors() as e:  # evaluated only when something was raised
        typer.echo(f"station: error: {e}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        typer.echo("station: interrupted", err=True)
        sys.exit(130)
    except Exception as e:  # click usage errors arrive here in non-standalone mode (typer vendors click)
        if type(e).__name__ == "Abort":
            sys.exit(130)
        if hasattr(e, "show") and isinstance(getattr(e, "exit_code", None), int):
            _usage_error(e)
        _internal_error(e)


def _usage_error(e) -> None:
    """A click usage error (bad option value, missing argument) as one line and exit 2."""
    message = e.format_message() if hasattr(e, "format_message") else str(e)
    ctx = getattr(e, "ctx", None)
    where = f"{ctx.command_path}: " if ctx is not None and getattr(ctx, "command_path", None) else ""
    typer.echo(f"station: error: {where}{' '.join(str(message).split())}", err=True)
    sys.exit(2 if e.exit_code in (1, 2) else e.exit_code)


def _internal_error(e: BaseException) -> None:
    """A crash is a fault, never the FAIL code: one line and exit 2; the traceback only with STATION_DEBUG=1."""
    import os
    import traceback

    if isinstance(e, OSError):  # a file or device the user named: say which, as the station's own errors do
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        typer.echo(f"station: error: {where}{e.strerror or e}", err=True)
        sys.exit(2)
    if os.environ.get("STATION_DEBUG"):
        traceback.print_exception(e)
    text = " ".join(str(e).split())[:300]
    hint = "" if os.environ.get("STATION_DEBUG") else " (STATION_DEBUG=1 shows the traceback)"
    typer.echo(f"station: error: internal error: {type(e).__name__}: {text}{hint}", err=True)
    sys.exit(2)
