"""The ``station`` command. Each command group lives in its own module and registers itself here.

Errors the station raises on purpose (``StationError``, bad model files, bad input) print one line
``station: error: ...`` and exit 2; a traceback is a bug."""

from __future__ import annotations

import contextlib
import importlib
import sys

# command -> (module defining ``register(app: typer.Typer) -> None`` or ``click_commands() -> {name: command}``,
# its one-line help for ``station --help``). Only the invoked command's module is imported (``station --help``
# imports none), and a click module's commands run without typer: start-up of every command (bench/startup.py;
# bench/startup.py). tests/cli/test_startup.py checks this table against what each module registers.
COMMANDS = {
    "solve": ("station.cli.solve_cmd", "Identify joint offsets, TCP, link geometry from touch samples."),
    "fk": ("station.cli.solve_cmd", "Tool pose (x, y, z in m; rx, ry, rz rotation vector in rad) for each row of "
                                    "joint readings."),
    "run": ("station.cli.run_cmd", "Run a procedure end of line: unattended, PASS/FAIL, exit 0 pass / 1 fail / 2 "
                                   "error."),
    "resume": ("station.cli.run_cmd", "Continue an interrupted session: robot re-verified, recorded samples kept, "
                                      "nothing repeated."),
    "restore": ("station.cli.run_cmd", "Write the session's calibration-backup.json (the calibration before its "
                                       "write-back) back into the robot, as a transaction: journaled (writeback "
                                       "kind=restore), signals held, read back."),
    "demo": ("station.cli.run_cmd", "Emulated robot with hidden offset errors and a socket: run zero_offsets end of "
                                    "line through the real client library, print recovered offsets next to the "
                                    "hidden truth, residuals and the report path."),
    "jog": ("station.cli.jog_cmd", "Jog the robot, touch reference points, record samples, watch the live solve, "
                                   "write back."),
    "report": ("station.cli.records_cmd", "Rebuild the HTML and JSON report of a session from its journal."),
    "panel": ("station.cli.panel_cmd", "Operator panel: sign in, scan the serial, START, live progress, full-screen "
                                       "PASS/FAIL, history."),
    "opcua": ("station.cli.opcua_cmd", "OPC UA server: object Station (State, Serial, Procedure, Step, Progress, "
                                       "Verdict, LastResult; Start(serial, procedure) -> session, Abort())."),
    "model": ("station.cli.model_cmd", "Kinematic models: built-in, model files, URDF (show, export, import)."),
    "mock": ("station.cli.mock_cmd", "Emulated robots (wire-level) and the simulated world."),
    "records": ("station.cli.records_cmd", "Calibration records per robot serial (list, show, export)."),
    "map": ("station.cli.map_cmd", "Correction map: measure the robot over a grid of actuator positions with a "
                                   "tracker, then command it and read it corrected (plan, build, apply, correct)."),
    "compensate": ("station.cli.compensate_cmd", "Compensated targets: joint (or corrected Cartesian) commands that "
                                                 "a controller with its nominal model turns into the calibrated "
                                                 "pose."),
    "iso9283": ("station.cli.iso_cmd", "ISO 9283 pose characteristics (AP, RP, vAP, AD, RD with confidence "
                                       "intervals) from commanded and attained poses."),
}


def load_commands(module: str) -> dict:
    """The commands ``module`` defines, by name: its ``click_commands()``, or what its ``register`` adds to a
    scratch Typer app."""
    mod = importlib.import_module(module)
    if hasattr(mod, "click_commands"):
        return mod.click_commands()
    import typer
    from typer.main import get_group

    scratch = typer.Typer(rich_markup_mode=None)
    scratch.callback()(lambda: None)  # a group even when the module registers one command
    mod.register(scratch)
    return get_group(scratch).commands


def __getattr__(name: str):
    """``app`` (the typer group of every command) is built on first use: a click command never imports typer."""
    if name in ("app", "LazyGroup"):
        from station.cli import group

        return getattr(group, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def fail(message: str, code: int = 2):
    """Print the one-line error and return the ``typer.Exit`` to raise."""
    import typer

    _err(f"station: error: {message}")
    return typer.Exit(code)


def _err(line: str) -> None:
    """One line whatever the message quotes: a control character read from a file (a key holding "\\r")
    is printed escaped, never as a line break."""
    if not line.isprintable():
        line = "".join(c if c.isprintable() else repr(c)[1:-1] for c in line)
    print(line, file=sys.stderr, flush=True)


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
    try:
        # in non-standalone mode click *returns* the code of a raised Exit instead of exiting
        rc = _run(sys.argv[1:])
        if isinstance(rc, int) and rc != 0:
            sys.exit(rc)
    except _input_errors() as e:  # evaluated only when something was raised
        _err(f"station: error: {e}")
        sys.exit(2)
    except KeyboardInterrupt:
        _err("station: interrupted")
        sys.exit(130)
    except Exception as e:  # click usage errors arrive here in non-standalone mode (typer vendors its own click)
        if type(e).__name__ == "Abort":
            sys.exit(130)
        if type(e).__name__ == "Exit" and isinstance(getattr(e, "exit_code", None), int):  # typer.Exit
            sys.exit(e.exit_code)
        if hasattr(e, "show") and isinstance(getattr(e, "exit_code", None), int):
            _usage_error(e)
        _internal_error(e)


_click_command_ran = False  # set by _run: console() may then end the process without the interpreter's teardown


def console() -> None:
    """The ``station`` console script: :func:`main`. After a click command (solve, fk) the process ends without
    the interpreter's teardown: freeing numpy and every module costs ~10 % of a solve's cpu (bench/startup.py),
    and they have closed their files; their output is flushed here, and a failed flush is a one-line error
    (a full disk under ``> out.csv``), never lost in silence. Other commands exit normally (their emulators,
    threads and atexit handlers need it). ``main()`` itself never does this: tests and scripts call it."""
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code
    if not _click_command_ran:
        sys.exit(code)
    if not isinstance(code, int):
        if code is not None:
            print(code, file=sys.stderr)
        code = 0 if code is None else 1
    import os

    try:
        sys.stdout.flush()
    except OSError as e:
        if not isinstance(e, BrokenPipeError):  # a reader that went away (| head) is not an error
            _err(f"station: error: standard output: {e.strerror or e}")
            code = 2
    with contextlib.suppress(OSError):
        sys.stderr.flush()
    os._exit(code)


def _run(args: list[str]):
    """``station NAME ...`` of a click-defined command runs it directly; everything else goes through typer."""
    if args and args[0] in COMMANDS:
        module = importlib.import_module(COMMANDS[args[0]][0])
        if hasattr(module, "click_commands"):
            global _click_command_ran
            _click_command_ran = True
            _one_blas_thread()
            command = module.click_commands()[args[0]]
            with _fewer_collections():
                return command.main(args[1:], prog_name=f"station {args[0]}", standalone_mode=False)
    _quiet_bus_libraries()  # not for the click commands: they open no bus, and logging costs ~10 ms to import
    from station.cli.group import app

    return app(standalone_mode=False)


def _one_blas_thread() -> None:
    """solve and fk do 12 x 12 to 150 x 12 linear algebra: BLAS worker threads only cost their start when numpy
    is imported (~10 % of a solve's cpu, bench/startup.py) and their spinning. One thread unless the user says
    otherwise; set only before numpy is imported (OpenBLAS reads it then), so never inside a process that already
    has numpy (a test) and whose children would inherit it."""
    import os

    if "numpy.linalg" not in sys.modules:  # not "numpy": station.lazy registers a module that is not loaded yet
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@contextlib.contextmanager
def _fewer_collections():
    """solve and fk allocate their start-up (numpy, the model, the station's modules: objects that live to the
    end of the process) and little else; Python's cyclic collector, every 700 allocations, would scan those same
    live objects again and again (~5 % of a solve's cpu, bench/startup.py). A collection every 100 000 keeps a
    long run's garbage cycles bounded still; the caller's setting is restored (main() runs inside tests)."""
    import gc

    before = gc.get_threshold()
    gc.set_threshold(100_000, *before[1:])
    try:
        yield
    finally:
        gc.set_threshold(*before)


def _usage_error(e) -> None:
    """A click usage error (bad option value, missing argument) as one line and exit 2."""
    ctx = getattr(e, "ctx", None)
    if type(e).__name__ == "NoArgsIsHelpError" and ctx is not None:  # bare ``station`` / ``station mock``
        print(ctx.get_help(), flush=True)
        sys.exit(2)
    message = e.format_message() if hasattr(e, "format_message") else str(e)
    where = f"{ctx.command_path}: " if ctx is not None and getattr(ctx, "command_path", None) else ""
    _err(f"station: error: {where}{' '.join(str(message).split())}")
    sys.exit(2 if e.exit_code in (1, 2) else e.exit_code)


def _internal_error(e: BaseException) -> None:
    """A crash is a fault, never the FAIL code: one line and exit 2; the traceback only with STATION_DEBUG=1."""
    import os
    import traceback

    if isinstance(e, OSError):  # a file or device the user named: say which, as the station's own errors do
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        _err(f"station: error: {where}{e.strerror or e}")
        sys.exit(2)
    if os.environ.get("STATION_DEBUG"):
        traceback.print_exception(e)
    text = " ".join(str(e).split())[:300]
    hint = "" if os.environ.get("STATION_DEBUG") else " (STATION_DEBUG=1 shows the traceback)"
    _err(f"station: error: internal error: {type(e).__name__}: {text}{hint}")
    sys.exit(2)
