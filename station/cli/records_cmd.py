"""``station records list|show|export`` (the calibration records database) and ``station report`` (rebuild the
HTML/JSON report of a session from its journal). Tables are for people: lengths in mm, angles in deg."""

from __future__ import annotations

import math
import os
from pathlib import Path

import typer
from rich import box
from rich.console import Console
from rich.markup import escape

from station.cli import COMMANDS
from station.cli.helpgroup import HelpGroup
from station.cli.tables import Col, print_table, wrap_lines
from station.units import human_of

records_app = typer.Typer(cls=HelpGroup, no_args_is_help=True, help=COMMANDS["records"][1])

DB_HELP = "Records database URL (default $STATION_DB, else sqlite:///$STATION_HOME/station.db)"


def _open(db: str | None):
    from station.cli import fail
    from station.records import open_records
    from station.robot.errors import StationError

    try:
        return open_records(db)
    except StationError as e:
        raise fail(str(e)) from None


def _mm(v) -> str:
    return "" if v is None or not math.isfinite(float(v)) else f"{float(v) * 1e3:.4f}"


def _human(v, unit: str | None) -> str:
    if v is None or not math.isfinite(float(v)):
        return ""
    return f"{float(v) * human_of(unit or 'm')[1]:.4f}"


def _hunit(unit: str | None) -> str:
    return human_of(unit)[0]


def _verdict(passed) -> str:
    return {True: "[green]PASS[/]", False: "[red]FAIL[/]"}.get(passed, "-")


def _console() -> Console:
    # a pipe or log file gets 160 columns instead of rich's 80: the tables stay readable in CI logs
    con = Console(highlight=False, soft_wrap=False)
    if not con.is_terminal and "COLUMNS" not in os.environ:
        con = Console(highlight=False, soft_wrap=False, width=160)
    return con


def _when(iso: str | None) -> str:
    """ISO time as 'YYYY-MM-DD HH:MM:SS' (UTC as the engine writes it) to keep tables narrow."""
    return (iso or "").replace("T", " ")[:19]


def _duration(started: str | None, finished: str | None) -> str:
    from datetime import datetime

    if not finished:
        return "(open)"
    try:
        sec = (datetime.fromisoformat(finished) - datetime.fromisoformat(started or "")).total_seconds()
    except ValueError:
        return "?"
    return f"{int(sec // 60)}m{int(sec % 60):02d}s"


NARROW = 120  # below this many columns the tables keep what an operator needs: serial/session and verdict


def _with_verdicts(rec, rows: list[dict]) -> list[dict]:
    """A completed session without pass/fail in the summary row: its verdict's own word (NO LIMITS: nothing to
    judge against, never a pass) from the stored session, not the bare "completed"."""
    from station.records import overall_status

    out = []
    for s in rows:
        if s["passed"] is None and s["status"] == "completed":
            s = {**s, "verdict_word": overall_status(rec.session(s["session"]).get("verdict"))}
        out.append(s)
    return out


SESSION_COLS = [Col("session"), Col("procedure", priority=3), Col("started", priority=2), Col("took", priority=4),
                Col("station", priority=5), Col("operator", priority=5), Col("samples", "right"),
                Col("rms before mm", "right", priority=3), Col("rms after mm", "right"),
                Col("verdict"), Col("written", priority=2)]


def _print_sessions(con: Console, title: str, rows: list[dict]) -> None:
    out = []
    for s in rows:
        wb = "-" if s["writeback_applied"] is None else (
            ("verified" if s["writeback_verified"] else "NOT verified") if s["writeback_applied"] else "not applied")
        out.append({"session": s["session"], "procedure": s["procedure"], "started": _when(s["started"]),
                    "took": _duration(s["started"], s["finished"]), "station": s["station"],
                    "operator": s["operator"], "samples": str(s["n_samples"]), "rms before mm": _mm(s["rms_before_m"]),
                    "rms after mm": _mm(s["rms_after_m"]),
                    "verdict": _verdict(s["passed"]) if s["passed"] is not None else (
                        s.get("verdict_word") or s["status"] or "-"), "written": wb})
    print_table(con, title, SESSION_COLS, out, style=_box(con))


def _box(con: Console):
    return box.SIMPLE_HEAD if con.width < NARROW else box.HEAVY_HEAD


@records_app.command("list")
def list_records(db: str = typer.Option(None, "--db", help=DB_HELP),
                 serial: str = typer.Option(None, "--serial", help="Only the sessions of this robot")) -> None:
    """List robots, or the sessions of one robot with --serial (readable at 80 columns: serials, session ids
    and verdicts are never cut)."""
    from station.cli import fail
    from station.records import RecordNotFound

    con = _console()
    with _open(db) as rec:
        if serial is None:
            robots = rec.robots()
            cols = [Col("serial"), Col("vendor", priority=2), Col("model"), Col("firmware", priority=3),
                    Col("sessions", "right"), Col("last session", priority=2), Col("last started", priority=1),
                    Col("last verdict")]
            rows = [{"serial": r["serial"], "vendor": r["vendor"], "model": r["model"], "firmware": r["firmware"],
                     "sessions": str(r["n_sessions"]), "last session": r["last_session"] or "",
                     "last started": _when(r["last_started"]), "last verdict": _verdict(r["last_passed"])}
                    for r in robots]
            print_table(con, f"Robots in {rec.url}", cols, rows, style=_box(con))
            if not robots:
                con.print("no records yet")
            return
        try:
            rec.robot(serial)
        except RecordNotFound as e:
            raise fail(str(e)) from None
        _print_sessions(con, f"Sessions of robot {serial}", _with_verdicts(rec, rec.sessions(serial)))


@records_app.command("show")
def show(serial: str = typer.Argument(..., help="Robot serial number"),
         db: str = typer.Option(None, "--db", help=DB_HELP),
         session: str = typer.Option(None, "--session", help="This session instead of the latest one"),
         trend: bool = typer.Option(False, "--trend", help="Each parameter across the robot's runs with its "
                                    "uncertainty, drift beyond 3 sigma flagged")) -> None:
    """One robot: identity, its sessions, and the latest (or --session) result, verdict and write-back;
    with --trend each parameter across runs."""
    from station.cli import fail
    from station.records import RecordNotFound

    con = _console()
    with _open(db) as rec:
        try:
            robot = rec.robot(serial)
            sessions = rec.sessions(serial)
            if session is not None:
                chosen = rec.session(session)
                if chosen.get("serial") != serial:
                    raise RecordNotFound(f"session {session!r} is not a session of robot {serial!r}")
            else:
                chosen = rec.session(sessions[-1]["session"]) if sessions else None
        except RecordNotFound as e:
            raise fail(str(e)) from None
        con.print(f"[bold]Robot {serial}[/]  {robot['vendor']} {robot['model']}  firmware {robot['firmware'] or '-'}"
                  f"  {robot['url']}")
        con.print(f"first seen {robot['first_seen']}, last seen {robot['last_seen']}, {robot['n_sessions']} session(s)")
        _print_sessions(con, "Sessions", _with_verdicts(rec, sessions))
        if trend:
            _show_trend(con, [rec.session(x["session"]) for x in sessions])
            return
        if chosen is None:
            return
        _show_session(con, chosen)


@records_app.command("sync")
def sync(sessions: list[str] = typer.Argument(None, help="Session ids or folders (default: every ended "
                                                          "session in $STATION_HOME/sessions not stored yet)"),
         db: str = typer.Option(None, "--db", help=DB_HELP + "; default: the URL each session's journal names")
         ) -> None:
    """Store sessions in the records database from their journals (e.g. after the database was down at the end
    of a run: the run said NOT STORED). Idempotent. Exit 2 if any session could not be stored."""
    import sys

    from station.publish import sync_sessions

    results = sync_sessions(list(sessions or []), db, log=lambda t: typer.echo(t, err=True))
    bad = 0
    for sid, what in results:
        if what.startswith("error: "):
            bad += 1
            typer.echo(f"station: error: session {sid}: {what[7:]}", err=True)
        else:
            typer.echo(f"{sid}: {what}")
    if not results:
        typer.echo("nothing to store")
    if bad:
        sys.exit(2)


def _show_trend(con: Console, docs: list[dict]) -> None:
    from station.records.trend import DRIFT_SIGMA, parameter_trend
    from station.report.analysis import load_session_model
    from station.report.content import param_unit

    model = load_session_model(docs[-1])[0] if docs else None
    trend = parameter_trend(docs)
    cols = [Col("parameter"), Col("started"), Col("value", "right"), Col("±σ", "right"), Col("unit"),
            Col("Δ/σ", "right", priority=1), Col("drift")]
    rows = []
    n_drift = 0
    for name, series in trend.items():
        for i, r in enumerate(series):
            unit = param_unit(name, {"unit": r["unit"]}, model)
            n_drift += bool(r["drift"])
            rows.append({"parameter": name if i == 0 or con.width < 60 else "", "started": _when(r["started"])[:16],
                         "value": _human(r["value"], unit) if r["identifiable"] else "not identifiable",
                         "±σ": _human(r["std"], unit) if r["identifiable"] else "", "unit": _hunit(unit),
                         "Δ/σ": "" if r["drift_sigma"] is None else f"{r['drift_sigma']:.1f}",
                         "drift": "[red]DRIFT[/]" if r["drift"] else (
                             f"model {r.get('model')}" if r.get("model_changed") else "")})
    print_table(con, f"Trend (drift: a change beyond {DRIFT_SIGMA:g} combined sigma from the previous run)", cols,
                rows, style=box.SIMPLE_HEAD)
    con.print(f"{n_drift} drift(s) beyond {DRIFT_SIGMA:g} σ" if n_drift else "no drift beyond 3 σ")


@records_app.command("export")
def export(fmt: str = typer.Option("csv", "--format", help="Format: csv (one row per session and parameter) or json"),
           since: str = typer.Option(None, "--since", help="Only sessions started at/after this ISO date or time "
                                     "(UTC unless a zone is given)"),
           serial: str = typer.Option(None, "--serial", help="Only this robot"),
           out: Path = typer.Option(None, "--out", help="Write to this file instead of stdout"),
           db: str = typer.Option(None, "--db", help=DB_HELP)) -> None:
    """Export sessions for analysis (SI units: m, rad; the unit of each value in its own column/field)."""
    import csv
    import io

    from station.cli import fail
    from station.records.trend import EXPORT_COLUMNS, export_rows, export_sessions, parse_since

    if fmt not in ("csv", "json"):
        raise fail(f"--format must be csv or json, got {fmt!r}")
    try:
        t0 = parse_since(since)
    except ValueError as e:
        raise fail(str(e)) from None
    with _open(db) as rec:
        if fmt == "json":
            from station.safeio import dumps_json  # strict JSON: a NaN/inf is null

            text = dumps_json({"format": "station-records-export/1", "units": "SI (m, rad)", "since": since,
                               "sessions": export_sessions(rec, serial, t0)}, indent=1, default=str) + "\n"
        else:
            buf = io.StringIO()
            w = csv.DictWriter(buf, fieldnames=EXPORT_COLUMNS, lineterminator="\n")
            w.writeheader()
            for r in export_rows(rec, serial, t0):
                w.writerow({k: "" if v is None else v for k, v in r.items()})
            text = buf.getvalue()
    if out is None:
        typer.echo(text, nl=False)
    else:
        try:
            out.write_text(text)
        except OSError as e:
            raise fail(f"{out}: {e.strerror or e}") from None


def _show_session(con: Console, s: dict) -> None:
    from station.records import measurement_status, overall_status
    from station.report.analysis import load_session_model
    from station.report.content import param_unit, steps_rows

    model, _ = load_session_model(s)  # joint kinds: a prismatic joint's offset is shown in mm

    con.print(f"\n[bold]Session {s['session']}[/]  {s.get('procedure') or ''}  started {s.get('started') or ''}"
              f"  station {s.get('station') or ''}  operator {s.get('operator') or ''}")
    result = s.get("result")
    if result:
        res = result.get("residuals") or {}
        title = (f"Result ({'converged' if result.get('converged') else 'NOT converged'}, rank {result.get('rank')} "
                 f"of {result.get('n_parameters')}; rms {_mm(res.get('rms_before_m'))} -> "
                 f"{_mm(res.get('rms_after_m'))} mm)")
        narrow = con.width < NARROW  # the reasons go below the table, wrapped at words, not into a thin column
        cols = [Col("parameter"), Col("nominal", "right", priority=1), Col("estimate", "right"),
                Col("±σ", "right"), Col("unit")] + ([] if narrow else [Col("note", text=True)])
        rows, reasons = [], []
        for name, p in (result.get("parameters") or {}).items():
            unit = param_unit(name, p, model)
            seen = bool(p.get("identifiable"))
            rows.append({"parameter": name, "nominal": _human(p.get("nominal"), unit),
                         "estimate": _human(p.get("value"), unit) if seen else ("not identifiable" if narrow else ""),
                         "±σ": _human(p.get("std"), unit), "unit": _hunit(unit),
                         "note": "" if seen else f"not identifiable: {p.get('reason') or '?'}"})
            if not seen:
                reasons.append(f"{name}: {p.get('reason') or '?'}")
        print_table(con, title, cols, rows, style=_box(con))
        if narrow and reasons:
            con.print("not identifiable (kept at nominal):")
            for r in reasons:
                for line in wrap_lines(r, con.width):
                    con.print(line, markup=False, highlight=False, soft_wrap=True)
    else:
        con.print("no solver result")
    verdict = s.get("verdict")
    if verdict:
        rows = []
        for m in verdict.get("measurements") or []:
            st = measurement_status(m)
            colour = {"PASS": "green", "FAIL": "red", "MARGINAL": "yellow"}[st]
            rows.append({"measurement": str(m.get("name")), "unit": str(m.get("unit") or ""),
                         "result": f"[{colour}]{st}[/]",
                         **{k: "" if m.get(k) is None else f"{float(m[k]):.4g}" for k in ("value", "low", "high")}})
        print_table(con, f"Verdict: {overall_status(verdict)}", [
            Col("measurement"), Col("value", "right"), Col("low", "right"), Col("high", "right"), Col("unit"),
            Col("result")], rows, style=_box(con))
    wb = s.get("writeback")
    if wb:
        before, after = wb.get("before") or {}, wb.get("after") or {}
        if wb.get("phase") == "exported":
            con.print(f"Write-back: exported to {', '.join(wb.get('files') or [])}, controller unchanged")
        params = (result or {}).get("parameters") or {}
        rows = []
        for name in dict.fromkeys([*before, *after]):
            unit = param_unit(name, params.get(name) or {}, model)
            rows.append({"value": name, "before": _human(before.get(name), unit),
                         "after": _human(after.get(name), unit), "unit": _hunit(unit)})
        print_table(con, f"Write-back ({'applied' if wb.get('applied') else 'not applied'}, "
                         f"{'verified' if wb.get('verified') else 'not verified'})",
                    [Col("value"), Col("before", "right"), Col("after", "right"), Col("unit")], rows, style=_box(con))
    steps = steps_rows(s)
    if steps:
        rows = []
        for st in steps:
            colour = {"done": "green", "skipped": "default"}.get(st["status"], "red")
            rows.append({"step": "  " * st["depth"] + escape(st["name"]), "runs": str(st["runs"]),
                         "outcome": f"[{colour}]{escape(st['outcome'])}[/]",
                         "time s": "" if st["duration_s"] is None else f"{st['duration_s']:.1f}",
                         "arguments / why not done": escape("; ".join([st["args"]] * bool(st["args"]) + st["notes"]))})
        print_table(con, "Steps", [Col("step"), Col("runs", "right"), Col("outcome"),
                                   Col("time s", "right", priority=1),
                                   Col("arguments / why not done", text=True, priority=2)], rows, style=_box(con))


def report(source: str = typer.Argument(..., help="Session id (in $STATION_HOME/sessions, as station resume "
                                          "takes it), session folder (holding journal.jsonl) or a journal file"),
           out: Path = typer.Option(None, "--out", help="Folder for report.html/report.json "
                                                        "(default: the session folder)")) -> None:
    """Rebuild the HTML and JSON report of a session from its journal."""
    from station.cli import fail
    from station.engine.runner import find_session
    from station.report import ReportError, write_report
    from station.robot.errors import ConfigError

    try:
        journal = find_session(source)  # the same lookup as station resume
    except ConfigError as e:
        raise fail(str(e)) from None
    from station.engine.journal import JournalError
    from station.engine.session_record import session_from_journal

    try:
        session = session_from_journal(journal)
    except JournalError as e:  # names the journal, the line and the field
        raise fail(str(e)) from None
    except (ValueError, OSError) as e:
        raise fail(f"{journal}: {e}") from None
    try:
        path = write_report(session, out or journal.parent)
    except (ReportError, OSError) as e:
        raise fail(str(e)) from None
    typer.echo(str(path))


def register(app: typer.Typer) -> None:
    app.add_typer(records_app, name="records")
    app.command("report")(report)
