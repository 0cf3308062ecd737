"""``station run``, ``station resume``, ``station demo``: end-of-line procedures from the command line.

Exit status: 0 PASS, 1 FAIL, 2 error (``station: error: ...``), 130 interrupted. PASS/FAIL is printed only
after the session record is stored in the records database."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from station.cli.model_options import PAYLOAD
from station.cli.run_options import DB, LIMITS, TOUCH


def _exit(code: int):
    # sys.exit, not typer.Exit: station.cli.main runs click with standalone_mode=False, where a typer.Exit comes
    # back as a return value that main() drops (every exit would be 0)
    sys.exit(code)


def _progress_bar(quiet: bool):
    """A rich progress bar on stderr; returns (callback, context manager)."""
    import contextlib

    if quiet or not sys.stderr.isatty():
        state = {"last": -1}

        def plain(done: int, total: int, text: str) -> None:
            if not quiet and done != state["last"] and (done == total or done % 5 == 0):
                typer.echo(f"  {done}/{total} samples", err=True)
            state["last"] = done

        return plain, contextlib.nullcontext()
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    prog = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    console=Console(stderr=True), transient=False)
    task = {"id": None}

    def cb(done: int, total: int, text: str) -> None:
        if task["id"] is None:
            task["id"] = prog.add_task("samples", total=total)
        prog.update(task["id"], completed=done, total=total, description=text[:48])

    return cb, prog


def preflight(robot: str, poses, holdout, cone, seed, touch, reference, limits, cell) -> None:
    """Every option and input file checked before any robot is opened or moved: one line, exit 2."""

    _options(poses, holdout, cone, reference, seed)  # each value read by its declaration (station.engine.declare)
    if touch is not None:
        from station.engine.declare import TOUCH

        TOUCH.read(touch)
    from station.robot.url import parse_url

    parse_url(robot)
    from station.engine.limits import load_limits

    load_limits(limits)
    if cell is not None:
        from station.engine.cell import load_cell

        load_cell(cell)


def _options(poses=None, holdout=None, cone=None, reference=None, seed=None, procedure=None, **given) -> dict:
    """The session options of the declared flags given (``station.cli.procedure_options``): the plan's
    (``--poses`` ...) and the procedures' own (``--tracker``, ``--grid`` ...; by parameter name in ``given``).
    ``procedure``: refuse a flag it does not take."""
    from station.cli.procedure_options import read_options

    return read_options({"poses": poses, "holdout": holdout, "cone": cone, "reference": reference, "seed": seed,
                         **given}, procedure)


def payload_option(text: str) -> dict:
    """``--payload 15kg[@x,y,z mm]`` (the declaration of ``station solve --payload``) as the procedure option
    ``{"mass": kg, "com": [x, y, z] m in the tool frame}``; one line, exit 2 on a bad value."""
    from station.procedures._calibration import PAYLOAD

    return PAYLOAD.read(text)


def _fmt(value: float | None, unit: str) -> str:
    return "-" if value is None else f"{value:.4g} {unit}"


def summary(out, echo=typer.echo) -> None:
    """Print result, verdict table, report path (no PASS/FAIL line: the caller prints it last)."""
    from station.units import human_of

    rec = out.record
    res = rec.get("result")
    if res:
        echo("parameters (identified value - nominal, 1-sigma):")
        for name, p in res["parameters"].items():
            if p.get("kind") == "point":
                continue
            u, k = human_of(p.get("unit") or "m")
            if p["identifiable"]:
                sd = "-" if p.get("std") is None else f"{p['std'] * k:.4f}"  # no ± is never printed as ± 0
                echo(f"  {name:14s} {(p['value'] - p['nominal']) * k:+10.4f} {u} ± {sd}")
            else:
                import textwrap  # the whole reason, wrapped at word boundaries, never cut mid-word

                line = f"  {name:14s} {'not identifiable':>14s}  ({p.get('reason') or ''})"
                echo("\n".join(textwrap.wrap(line, 118, subsequent_indent=" " * 34, break_long_words=False)))
        r = res["residuals"]
        echo(f"residuals: RMS {r['rms_before_m'] * 1e3:.3f} mm before -> {r['rms_after_m'] * 1e3:.3f} mm after"
             + (f"; held-out RMS {res['holdout']['rms_m'] * 1e3:.3f} mm" if res.get("holdout") else ""))
    verdict = rec.get("verdict")
    if verdict:
        echo(f"verdict (limits {rec.get('limits', {}).get('version') if rec.get('limits') else '?'}):")
        for m in verdict["measurements"]:
            lo, hi = ("" if m.get(k) is None else m[k] for k in ("low", "high"))
            bounds = f"[{lo:>6} .. {hi:<6}]"
            flag = "PASS" if m["passed"] else "FAIL"
            if m["passed"] and m.get("marginal"):
                flag = "MARGINAL"
            value = m.get("value")
            echo(f"  {m['name']:16s} {'-' if value is None else format(value, '.4g'):>10} {m.get('unit', ''):5s} "
                 f"{bounds:18s} {flag}")
    wb = rec.get("writeback")
    if wb:
        echo(f"write-back: applied={wb.get('applied')} verified={wb.get('verified')} {wb.get('note') or ''}")
    echo(f"session:  {out.session}  ({out.folder / 'journal.jsonl'})")
    if res and (out.folder / "result.json").is_file():
        echo(f"result:   {out.folder / 'result.json'}  (station model export --calibration {out.session} "
             "--format urdf writes the calibrated robot)")
    if out.report:
        echo(f"report:   {out.report}")


def _finish(out, next_step=None) -> None:
    """The last lines of a run: the summary, then PASS/FAIL (exit 0/1) only for a completed, stored session;
    otherwise one ``station: error:`` line, what to do next (only a command that will work), and the exit code
    (2 error or NOT STORED, 130 interrupted)."""
    from station.robot.errors import StationError

    if out.status == "completed" and out.verdict == "NO LIMITS":  # nothing to judge against: never a PASS
        summary(out)
        typer.echo("NO LIMITS")
        _exit(2)
    if out.status == "completed" and out.passed is not None and out.stored:
        summary(out)
        if out.passed is False and next_step is not None:
            for line in next_step(out):
                typer.echo(line)
        typer.echo(out.verdict)
        _exit(out.exit_code)
    summary(out, echo=lambda s: typer.echo(s, err=True))
    err = out.error
    msg = (str(err) or type(err).__name__) if err is not None else "the session did not reach a verdict"
    if out.store_error is not None and out.record.get("status") == "completed":
        # the run itself completed: its journal is complete, only the record is missing from the database
        typer.echo(f"station: error: record not stored: {out.store_error}", err=True)
        typer.echo(f"station: the journal is complete; store it later with: station records sync {out.session}",
                   err=True)
        typer.echo("NOT STORED")
        _exit(2)
    if out.status == "interrupted":
        typer.echo(f"station: interrupted; continue with: station resume {out.session}", err=True)
        _exit(130)
    if err is not None and not isinstance(err, (StationError, ValueError, OSError)):
        raise err  # a bug: keep the traceback
    typer.echo(f"station: error: {msg}", err=True)
    if out.record.get("status") == "completed":  # e.g. the report could not be written: the record is stored
        typer.echo(f"station: the record is stored; rebuild the report with: station report {out.folder}", err=True)
    elif "station restore" in msg:  # the message already names the one command that helps (resume would refuse)
        pass
    elif "nothing moved" in msg:  # refused before any motion: a resume would meet the same refusal
        typer.echo("station: nothing moved; start a new run with the change named above", err=True)
    else:
        typer.echo(f"station: the journal is kept; continue with: station resume {out.session}", err=True)
    _exit(2)


def _shipped() -> list[str]:
    """The shipped procedures, from the procedures folder: the help lists every one, never a copy that ages."""
    from station.engine.procedure import shipped_names

    return shipped_names()


def run(
    procedure: str = typer.Argument(..., help="Shipped procedure (" + ", ".join(_shipped()) + ") or a procedure "
                                    ".py file; station run PROCEDURE --help lists its options and measurements."),
    robot: str = typer.Option(..., "--robot", help="Robot URL, e.g. ur://127.0.0.2?model=ur5e"),
    serial: str = typer.Option(..., "--serial", help="Serial number of the robot under calibration."),
    limits: Path = LIMITS,
    db: str = DB,
    apply: bool = typer.Option(False, "--apply", help="Write identified joint offsets back (two-phase)."),
    cell: Path = typer.Option(None, "--cell", help="Cell file (default $STATION_CELL, then ./cell.yaml)."),
    operator: str = typer.Option(None, "--operator", help="Who runs it (default: login name)."),
    touch: str = TOUCH,
    identify: str = typer.Option(None, "--identify", help="Parameter groups to solve for instead of the "
                                 "procedure's own (zero_offsets: offsets, dh_full: offsets,dh,tcp), e.g. "
                                 "offsets,tcp; as station solve --identify."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    **declared,
) -> None:
    """Run a procedure end of line: unattended, PASS/FAIL, exit 0 pass / 1 fail / 2 error. The procedure's own
    options (--poses, --tracker, ...) are the ones it declares."""
    from station.api import run as start
    from station.cli.nextstep import suggest
    from station.cli.procedure_options import own_given
    from station.engine.procedure import load_procedure

    proc = load_procedure(procedure)
    declared.update(own_given())  # the options only this procedure declares (a site's own procedure)
    plan = {k: declared.pop(k, None) for k in ("poses", "holdout", "cone", "reference", "seed")}
    preflight(robot, plan["poses"], plan["holdout"], plan["cone"], plan["seed"], touch, plan["reference"], limits,
              cell)
    options = _options(**plan, procedure=proc, **declared)
    if identify is not None:
        from station.cli.solve_cmd import check_identify

        options["identify"] = check_identify(identify)
    cb, bar = _progress_bar(quiet)
    with bar:
        out = start(proc, robot, serial, limits=limits, db=db, apply=apply, cell=cell, operator=operator,
                    options=options, touch=touch, progress=cb,
                    log=lambda s: typer.echo(s, err=True))
    cell_text = None if cell is None else str(cell)
    _finish(out, lambda o: suggest(o, robot=robot, serial=serial, cell=cell_text, identify=identify))


def resume_cmd(
    session: str = typer.Argument(..., help="Session id (in $STATION_HOME/sessions) or its folder/journal."),
    db: str = typer.Option(None, "--db", help="Records database URL (default: the one the session used)."),
    tracker: str = typer.Option(None, "--tracker", help="The session's measuring instrument at a new address "
                                "(e.g. tcp://127.0.0.1:5301 after a restart); it must be the same instrument."),
    payload: str = PAYLOAD,
    procedure: Path = typer.Option(None, "--procedure", help="The session's procedure file, when it is neither "
                                   "shipped nor in a $STATION_PROCEDURES folder (its sha256 must be the "
                                   "journaled one)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Continue an interrupted session: robot re-verified, recorded samples kept, nothing repeated."""
    from station.api import resume

    # --payload on a resume is only checked: the journaled one is used, another one is refused
    given = payload_option(payload) if payload is not None else None
    cb, bar = _progress_bar(quiet)
    with bar:
        out = resume(session, db=db, progress=cb, log=lambda s: typer.echo(s, err=True),
                     instruments={"tracker": tracker} if tracker is not None else None, payload=given,
                     procedure=procedure)
    _finish(out)


def restore_cmd(
    session: str = typer.Argument(..., help="Session id (in $STATION_HOME/sessions) or its folder/journal."),
    db: str = typer.Option(None, "--db", help="Records database URL (default: the one the session used)."),
) -> None:
    """Write the session's calibration-backup.json (the calibration before its write-back) back into the robot,
    as a transaction: journaled (writeback kind=restore), signals held, read back. Then the record is updated."""
    from station.engine.runner import restore
    from station.publish import store_record

    done = restore(session, log=lambda s: typer.echo(s, err=True))
    typer.echo("device calibration (SI: rad, m for prismatic joints): before -> restored (read back)")
    for name, value in done["readback"].items():
        typer.echo(f"  {name:12s} {done['before'].get(name, float('nan')):+.9f} -> {value:+.9f}")
    typer.echo(f"restored: session {done['session']}: backup written back and read back")
    try:
        store_record(done["record"], db if db is not None else done["db"])
    except Exception as e:
        typer.echo(f"station: error: record not updated: {e}; store it later with: station records sync "
                   f"{done['session']}", err=True)
        _exit(2)


def _demo_help() -> str:
    from station.mocks.plug import demo_buses

    return f"Bus to demonstrate: {', '.join(demo_buses())} (an emulator with a demo world)."


def demo(
    robot: str = typer.Option("ur", "--robot", help=_demo_help()),
    time_mode: str = typer.Option("instant", "--time", help="Emulated motion: instant or realtime."),
    seed: int = typer.Option(5, "--seed", help="Seed of the hidden errors."),
) -> None:
    """Emulated robot with hidden offset errors and a socket: run zero_offsets end of line through the real
    client library, print recovered offsets next to the hidden truth, residuals and the report path."""
    _exit(run_demo(robot, time_mode=time_mode, seed=seed))


# ---- the demo: a world with hidden errors, an emulator for it (station.mocks.launch), zero_offsets ----------
# The station side never imports the mocks; this glue (the CLI) does. Which buses have a demo, their model and
# zero_offsets' options there come from the emulators' plugs (station.mocks.plug, entry points).
def __getattr__(name: str):
    """``BUS_MODELS`` / ``BUS_OPTIONS``: bus -> demo model / demo procedure options, from the plugs."""
    if name in ("BUS_MODELS", "BUS_OPTIONS"):
        from station.mocks.plug import demo_buses

        return {bus: (p.demo.model if name == "BUS_MODELS" else dict(p.demo.options))
                for bus, p in demo_buses().items()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _demo_plug(bus: str):
    from station.mocks.plug import demo_buses
    from station.robot.errors import ConfigError

    buses = demo_buses()
    if bus not in buses:
        raise ConfigError(f"--robot must be one of {', '.join(buses)}, got {bus!r}")
    return buses[bus]


def demo_world(bus: str, seed: int, time_mode: str = "instant", sigma_deg: float | None = None) -> dict:
    """World document (SI) with hidden joint zero offsets only (what zero_offsets identifies)."""
    import math

    import numpy as np

    from station.kinematics import load_model
    from station.mocks.world.world import default_doc

    demo = _demo_plug(bus).demo
    sigma_deg = demo.sigma_deg if sigma_deg is None else sigma_deg
    m = load_model(demo.model)
    rng = np.random.default_rng(seed)
    doc = default_doc(demo.model, seed)
    doc["description"] = f"demo world for {demo.model} on {bus}: hidden joint zero offsets"
    doc["errors"] = {"explicit": {f"offset.j{i + 1}": float(rng.normal(0, math.radians(sigma_deg)))
                                  if j.revolute else float(rng.normal(0, 0.1e-3)) for i, j in enumerate(m.joints)}}
    doc["motion"]["time_mode"] = time_mode
    doc["buses"] = {"ur": {"serial": f"2023550{seed:04d}"}, "dynamixel": {"ids": [11, 12, 13, 14]},
                    "canopen": {"nodes": list(range(1, m.n_joints + 1))}}
    for key, value in demo.world.items():
        doc[key] = {**doc.get(key, {}), **value} if isinstance(value, dict) else value
    return doc


def write_demo_files(bus: str, folder: Path, seed: int, time_mode: str) -> tuple[Path, Path, str]:
    """World file (the hidden truth) and the station's cell file for it; returns (world, cell, serial)."""
    import yaml

    from station.mocks.world import World

    folder.mkdir(parents=True, exist_ok=True)
    doc = demo_world(bus, seed, time_mode)
    world_path, cell_path = folder / f"{bus}-world.yaml", folder / f"{bus}-cell.yaml"
    world_path.write_text("# demo world (station-world/1), SI units; the hidden truth of the demo\n"
                          + yaml.safe_dump(doc, sort_keys=False))
    world = World.from_file(world_path)
    cell_path.write_text("# station cell (station-cell/1), lengths in m\n"
                         + yaml.safe_dump(world.station_cell(), sort_keys=False))
    serial = doc["buses"].get(bus, {}).get("serial") or f"DEMO-{bus.upper()}-{seed:04d}"
    return world_path, cell_path, serial


def run_demo(bus: str, *, time_mode: str = "instant", seed: int = 5, quiet: bool = False) -> int:
    import math
    import os
    import time

    from station.api import run as start
    from station.mocks.launch import launch
    from station.mocks.plug import CHILD
    from station.mocks.world import World
    from station.robot.errors import ConfigError

    if time_mode not in ("instant", "realtime"):
        raise ConfigError(f"--time must be instant or realtime, got {time_mode!r}")
    plug = _demo_plug(bus)
    home = Path(os.environ.get("STATION_HOME") or "./station-data")
    world_path, cell_path, serial = write_demo_files(bus, home / "demo", seed, time_mode)
    hidden = World.from_file(world_path).hidden()
    typer.echo(f"demo: {plug.demo.model} on {bus}, hidden errors in {world_path}")
    t0 = time.monotonic()
    # a child process where the emulator can run as one (realtime: its own GIL)
    with launch(bus, world_path, serial=serial, process=CHILD in plug.modes) as emu:
        url = emu.url + plug.demo.query
        typer.echo(f"demo: emulator up, robot URL {url}")
        if "power_on=yes" in url:
            typer.echo("demo: the controller boots with the arm powered off, as a real one; power_on=yes in the URL "
                       "lets the station power it on and release the brakes")
        cb, bar = _progress_bar(quiet)
        with bar:
            out = start("zero_offsets", url, serial, cell=cell_path, options=dict(plug.demo.options),
                        progress=cb, log=lambda s: typer.echo(s, err=True))
    if out.status != "completed" or out.passed is None:
        _finish(out)  # NO LIMITS too: exits
    res = out.record["result"]
    typer.echo("")
    typer.echo("joint zero offsets: hidden truth (world file) vs. recovered (deg)")
    typer.echo(f"  {'parameter':12s} {'truth':>10s} {'recovered':>10s} {'± 1σ':>8s} {'error':>9s}  ")
    from station.kinematics import load_model

    model = load_model(plug.demo.model)
    for name, p in res["parameters"].items():
        if not name.startswith("offset."):
            continue
        truth = math.degrees(hidden.get(name, 0.0))
        if p["identifiable"]:
            v, sd = math.degrees(p["value"]), math.degrees(p["std"])
            enc = model.joints[int(name[8:]) - 1].encoder
            count = math.degrees(1 / (enc.counts_per_unit * enc.gear)) if enc else 0.0
            # a joint that hardly moves between poses reads with the same rounding every time: half an encoder
            # count is a floor under the error that no spread of poses shows in sigma
            ok = abs(v - truth) <= 3 * sd + count / 2
            typer.echo(f"  {name:12s} {truth:10.4f} {v:10.4f} {sd:8.4f} {v - truth:+9.4f}  "
                       f"({abs(v - truth) / sd if sd else 0:.1f} σ{'' if count < 1e-3 else f', count {count:.3f}'})"
                       f" {'ok' if ok else 'OFF'}")
        else:
            typer.echo(f"  {name:12s} {truth:10.4f} {'—':>10s}  not identifiable: {p.get('reason') or ''}")
    typer.echo("")
    summary(out)
    typer.echo(f"time:     {time.monotonic() - t0:.1f} s")
    typer.echo("PASS" if out.passed else "FAIL")
    return out.exit_code


def register(app: typer.Typer) -> None:
    from station.cli.procedure_options import RunCommand, with_declared_flags

    app.command("run", cls=RunCommand)(with_declared_flags(run))
    app.command("resume")(resume_cmd)
    app.command("restore")(restore_cmd)
    app.command("demo")(demo)
