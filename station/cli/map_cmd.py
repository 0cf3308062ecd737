"""``station map plan|build|apply|correct``: the configuration-space correction map (docs/map.md).

CSV files: actuator columns ``x1..xN`` (m for a prismatic actuator, rad for a revolute one, unless the header
says ``x1[mm]``, ``x4[deg]``), pose columns ``x,y`` (planar robot) or ``x,y,z`` / ``x,y,z,rx,ry,rz``
(position, rotation vector; robot base frame; m and rad unless the header says a unit). Other columns are
ignored; ``#`` lines are comments. Output is SI with plain headers unless ``--units mm,deg``."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import time
from pathlib import Path

import typer

from station.cli import COMMANDS
from station.cli.helpgroup import HelpGroup
from station.cli.model_options import PAYLOAD
from station.lazy import lazy_module
from station.robot.errors import ConfigError
from station.safeio import DuplicateKeyError, loads_strict
from station.samplesfile import ANGLE_UNITS, LENGTH_UNITS, SamplesFileError, Table, read_table

np = lazy_module("numpy")  # imported on first use (station.lazy: start-up of every command)

map_app = typer.Typer(cls=HelpGroup, no_args_is_help=True, help=COMMANDS["map"][1])

POSE_NAMES = ("x", "y", "z", "rx", "ry", "rz")
_ACT = re.compile(r"^x(\d+)$")


def _fail(msg: str) -> ConfigError:
    return ConfigError(msg)


# ---- units and CSV --------------------------------------------------------------------------------
def _units(text: str | None) -> tuple[float, str, float, str]:
    """Output units: (length factor, name, angle factor, name); SI (plain headers) when None."""
    if text is None or text.strip().lower() in ("si", "m,rad"):
        return 1.0, "", 1.0, ""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or parts[0] not in LENGTH_UNITS or parts[1] not in ANGLE_UNITS:
        raise _fail(f"--units {text!r}: expected LENGTH,ANGLE (m|mm|cm|um, rad|deg|mrad) or SI")
    return LENGTH_UNITS[parts[0]], parts[0], ANGLE_UNITS[parts[1]], parts[1]


def _header(name: str, angle: bool, units) -> str:
    _, ln, _, an = units
    unit = an if angle else ln
    return f"{name}[{unit}]" if unit else name


def _write_csv(path: Path, header: list[str], rows: np.ndarray, scale: np.ndarray) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in np.atleast_2d(rows):
        w.writerow([f"{v / s:.15g}" for v, s in zip(r, scale, strict=True)])
    _write_text(path, buf.getvalue())


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        raise _fail(f"{path}: cannot write ({e.strerror or e})") from None


def _read(path: Path) -> Table:
    try:
        t = read_table(path)
    except SamplesFileError as e:
        raise _fail(str(e)) from None
    if not t.rows:
        raise _fail(f"{path}: no data rows")
    return t


def _column(t: Table, name: str, kind: str) -> np.ndarray:
    """Column ``name`` in SI; ``kind`` is "length" or "angle"."""
    k, col = t.columns[name]
    where = f"{t.path}:{t.header_line}"
    factor = 1.0
    if col.unit is not None:
        table, other = (LENGTH_UNITS, ANGLE_UNITS) if kind == "length" else (ANGLE_UNITS, LENGTH_UNITS)
        if col.unit in table:
            factor = table[col.unit]
        elif col.unit in other:
            expect = "a length (m, mm, cm, um)" if kind == "length" else "an angle (rad, deg, mrad)"
            raise _fail(f"{where}: column {col.header!r}: its unit must be {expect}")
        else:
            raise _fail(f"{where}: column {col.header!r}: unknown unit {col.unit!r}")
    out = np.empty(len(t.rows))
    for i, row in enumerate(t.rows):
        s = row[k]
        try:
            v = float(s)
        except ValueError:
            raise _fail(f"{t.where(i)}: column {col.header!r}: not a number ({s!r})") from None
        if not np.isfinite(v):
            raise _fail(f"{t.where(i)}: column {col.header!r}: not a finite number ({s!r})")
        out[i] = v * factor
    return out


def _actuators(t: Table, model) -> np.ndarray:
    n = model.n_joints
    have = sorted(int(m.group(1)) for c in t.columns if (m := _ACT.match(c)))
    extra = [k for k in have if not 1 <= k <= n]
    if extra:
        raise _fail(f"{t.path}: wrong columns: x{extra[0]} but model {model.name} has {n} actuators (x1..x{n})")
    missing = [k for k in range(1, n + 1) if k not in have]
    if missing:
        raise _fail(f"{t.path}: missing column 'x{missing[0]}' (model {model.name} has {n} actuators: x1..x{n})")
    return np.column_stack([_column(t, f"x{k + 1}", "angle" if model.joints[k].revolute else "length")
                            for k in range(n)])


def _pose(t: Table, model, what: str) -> tuple[np.ndarray, tuple[str, ...]]:
    from station.solver.map import MapError, check_columns

    cols = tuple(c for c in POSE_NAMES if c in t.columns)
    rot = [c for c in ("rx", "ry", "rz") if c in cols]
    if rot and len(rot) != 3:
        miss = [c for c in ("rx", "ry", "rz") if c not in cols]
        raise _fail(f"{t.path}: missing column {miss[0]!r} (a rotation vector needs rx, ry, rz)")
    try:
        cols = check_columns(model, cols, what)
    except MapError as e:
        raise _fail(f"{t.path}: {e}") from None
    return np.column_stack([_column(t, c, "angle" if c.startswith("r") else "length") for c in cols]), cols


def _instrument(t: Table, model, x: np.ndarray, samples: Path, frame: str):
    """Poses of an instrument's CSV export (its own frame) -> base frame: (pose, columns, Registration|None)."""
    from station.solver.map import FULL, MapError, to_vectors
    from station.solver.map.register import register

    if frame not in ("fit", "base"):
        raise _fail(f"--frame {frame!r}: expected fit or base")
    if len(t.rows) != len(x):
        raise _fail(f"{t.path}: {len(t.rows)} measurements for {len(x)} samples in {samples}: give one row per "
                    "sample, in the same order")
    pose, cols = _pose(t, model, "measurements")
    if frame == "base":
        return pose, cols, None
    try:
        if cols not in (FULL, ("x", "y", "z")):
            raise MapError("registration of a planar robot's measurements is not supported: give --frame base")
        res = model.fk_solve(x) if getattr(model, "kind", "") == "parallel" else None
        if res is not None and not res.ok.all():
            i = int(np.flatnonzero(~res.ok)[0])
            raise MapError(f"sample {i + 1}: {res.reason[i]}", i)
        nominal = to_vectors(res.T if res is not None else model.fk(x), FULL)
        reg = register(nominal if cols == FULL else nominal[:, :3], pose, cols)
    except MapError as e:
        raise _row_error(e, t) from None
    return reg.to_base(pose, cols), cols, reg


def _model(name: str, payload: str | None = None):
    from station.kinematics import load_model

    m = load_model(name)  # ModelFileError -> one line in station.cli.main
    if payload:
        if not hasattr(m, "with_payload"):
            raise _fail(f"--payload: model {m.name} ({getattr(m, 'kind', '?')}) has no compliance terms for a "
                        "payload to load; leave --payload out")
        from station.cli.model_options import parse_payload

        m = m.with_payload(*parse_payload(payload))
    return m


def _load_map(path: Path):
    from station.solver.map import CorrectionMap, MapError

    try:
        doc = loads_strict(Path(path).read_text(), str(path))
    except FileNotFoundError:
        raise _fail(f"{path}: no such file") from None
    except DuplicateKeyError as e:
        raise _fail(str(e)) from None
    except (OSError, UnicodeDecodeError) as e:
        raise _fail(f"{path}: cannot read ({e})") from None
    except json.JSONDecodeError as e:
        raise _fail(f"{path}: line {e.lineno}: not valid JSON") from None
    except ValueError as e:  # NaN/Infinity: Python's json reads them, JSON has no such numbers
        raise _fail(f"{path}: {e}") from None
    try:
        return CorrectionMap.from_dict(doc, str(path))
    except MapError as e:
        raise _fail(str(e)) from None


def _row_error(e, t: Table) -> ConfigError:
    """A MapError about row i of ``t`` as ``FILE:LINE: ...``."""
    row = getattr(e, "row", None)
    if row is not None and 0 <= row < len(t.lines):
        msg = re.sub(r"^(sample|target|reading|configuration) \d+: ", "", str(e))
        return _fail(f"{t.where(row)}: {msg}")
    return _fail(f"{t.path}: {e}")


def _lookup_cost(cmap, n: int = 20000) -> float:
    """Seconds per query of the vectorised summand lookup, over random configurations in the domain."""
    rng = np.random.default_rng(0)
    x = rng.uniform(cmap.domain_lower, cmap.domain_upper, (n, cmap.n))
    t0 = time.perf_counter()
    cmap.summand(x)
    return (time.perf_counter() - t0) / n


def _human(v: float, revolute: bool) -> str:
    return f"{np.degrees(v):.4f} deg" if revolute else f"{v * 1e3:.4f} mm"


def _q_values(grid: str, m, exclude_ends: bool) -> list[int]:
    """``--grid Q`` or ``Q1,...,QN``, one Q per actuator."""
    try:
        qs = [int(v) for v in grid.split(",")]
    except ValueError:
        raise _fail(f"--grid {grid!r}: expected an integer Q or one per actuator (Q1,...,Q{m.n_joints})") from None
    if len(qs) not in (1, m.n_joints):
        raise _fail(f"--grid {grid!r}: one Q or {m.n_joints} (one per actuator)")
    if any(q < 1 for q in qs) or (exclude_ends and any(q < 2 for q in qs)):
        raise _fail(f"--grid {grid!r}: Q must be at least {2 if exclude_ends else 1}"
                    f"{' without the interval ends' if exclude_ends else ''}")
    return qs * m.n_joints if len(qs) == 1 else qs


# ---- commands ------------------------------------------------------------------------------------
@map_app.command("plan")
def plan_command(
    model: str = typer.Option(..., "--model", help="Built-in model name or model file"),
    grid: str = typer.Option(..., "--grid", help="Q: sub-intervals per actuator (Q+1 levels), or Q1,Q2,...,QN"),
    exclude_ends: bool = typer.Option(False, "--exclude-ends", help="Leave out the interval ends (Q-1 levels)"),
    mesh: str = typer.Option("grid", "--mesh", help="Mesh: grid (multilinear) or simplex (Kuhn simplices, "
                                                        "barycentric)"),
    out: Path = typer.Option(..., "--out", help="CSV of configurations x1..xN to visit"),
    units: str = typer.Option(None, "--units", help="Output units LENGTH,ANGLE (default SI, plain headers)"),
) -> None:
    """Plan the configurations to measure: a grid over each actuator's range (those the model cannot reach or
    assemble are left out, each with the reason)."""
    from station.solver.map import MESHES, plan

    m = _model(model)
    if mesh not in MESHES:
        raise _fail(f"--mesh {mesh!r}: expected grid or simplex")
    try:
        p = plan(m, _q_values(grid, m, exclude_ends), exclude_ends=exclude_ends, mesh=mesh)
    except ValueError as e:
        raise _fail(str(e)) from None
    if len(p.x) == 0:
        raise _fail(f"model {m.name}: none of the {len(p.dropped)} grid configurations can be assembled")
    u = _units(units)
    kinds = [j.revolute for j in m.joints]
    _write_csv(out, [_header(f"x{k + 1}", kinds[k], u) for k in range(m.n_joints)], p.x,
               np.array([u[2] if r else u[0] for r in kinds]))
    levels = "x".join(str(len(lv)) for lv in p.levels)
    typer.echo(f"plan: {len(p.x)} configurations of {m.name} ({levels} levels, mesh {mesh}"
               f"{', without interval ends' if exclude_ends else ''}) -> {out}")
    if len(p.dropped):
        typer.echo(f"left out: {len(p.dropped)} configurations (not assemblable, or too near the workspace boundary "
                   f"or a singularity):")
        for x, why in list(zip(p.dropped, p.reasons, strict=True))[:10]:
            vals = ", ".join(_human(v, r) for v, r in zip(x, kinds, strict=True))
            typer.echo(f"  [{vals}]: {why}")
        if len(p.dropped) > 10:
            typer.echo(f"  ... and {len(p.dropped) - 10} more")


@map_app.command("build")
def build_command(
    model: str = typer.Option(..., "--model", help="Built-in model name or model file"),
    payload: str = PAYLOAD,
    samples: Path = typer.Option(..., "--samples", help="CSV: x1..xN and the measured pose (base frame)"),
    calibration: Path = typer.Option(None, "--calibration", help="Result JSON of station solve: map on top of it"),
    mesh: str = typer.Option("grid", "--mesh", help="Mesh: grid (multilinear) or simplex (barycentric), as planned"),
    grid: str = typer.Option(None, "--grid", help="The plan's Q (checks every sample is on its grid); "
                                                  "default: the grid is read off the samples"),
    exclude_ends: bool = typer.Option(False, "--exclude-ends", help="With --grid: the plan left out the ends"),
    measurements: Path = typer.Option(None, "--measurements", help="An instrument's CSV export (x,y,z[,rx,ry,rz] "
                                      "in ITS frame, one row per samples row, same order); --samples then needs "
                                      "only x1..xN"),
    frame: str = typer.Option("fit", "--frame", help="With --measurements: fit (register the instrument frame to "
                              "the base frame by best fit) or base (already in the base frame)"),
    out: Path = typer.Option(..., "--out", help="The map (station-map/1 JSON)"),
) -> None:
    """Build the correction map from measured samples: at each, the actuator change the nominal model needs to
    explain the measured pose, interpolated between them (docs/map.md has the method and its notation)."""
    from station.solver import CalibrationResult
    from station.solver.map import MESHES, MapError, build_map, grid_levels

    m = _model(model, payload)
    if mesh not in MESHES:
        raise _fail(f"--mesh {mesh!r}: expected grid or simplex")
    levels = None
    if grid is not None:
        try:
            levels = grid_levels(m.lower, m.upper, _q_values(grid, m, exclude_ends), exclude_ends)
        except ValueError as e:
            raise _fail(f"--grid {grid!r}: {e}") from None
    cal, source = None, None
    if calibration is not None:
        try:
            res = CalibrationResult.from_dict(loads_strict(Path(calibration).read_text(), str(calibration)))
            res.calibrated(m)
        except FileNotFoundError:
            raise _fail(f"{calibration}: no such file") from None
        except DuplicateKeyError as e:
            raise _fail(str(e)) from None
        except json.JSONDecodeError as e:
            raise _fail(f"{calibration}: line {e.lineno}: not valid JSON") from None
        except (OSError, ValueError, KeyError) as e:
            raise _fail(f"{calibration}: {str(e).strip(chr(34) + chr(39))}") from None
        cal, source = res.values("model"), calibration.name
    t = _read(samples)
    x = _actuators(t, m)
    registration = None
    if measurements is None:
        pose, cols = _pose(t, m, "samples")
    else:
        t = _read(measurements)
        pose, cols, registration = _instrument(t, m, x, samples, frame)
    try:
        cmap = build_map(m, x, pose, cols, mesh=mesh, levels=levels, calibration=cal, calibration_source=source)
    except MapError as e:
        raise _row_error(e, t) from None
    if registration is not None:
        cmap.statistics["registration"] = registration.to_dict()
    cost = _lookup_cost(cmap)
    cmap.statistics["lookup_seconds_per_query"] = cost
    from station.safeio import write_atomic

    write_atomic(out, cmap.dumps())  # strict JSON, atomic; unwritable: one line, exit 2
    s = cmap.statistics
    kinds = [j.revolute for j in m.joints]
    typer.echo(f"map: {s['n_samples']} samples on {s['n_measured_nodes']} of {s['n_nodes']} grid nodes "
               f"({s['n_filled_nodes']} filled by continuation), mesh {mesh}, pose {','.join(cols)}"
               f"{', on top of calibration ' + source if source else ''}")
    typer.echo("largest correction: " + ", ".join(
        f"x{k + 1} {_human(v, kinds[k])}" for k, v in enumerate(s["summand_max"])))
    if registration is not None:
        v = registration.to_dict()["instrument_in_base"]
        typer.echo(f"instrument frame in the base frame (best fit of {registration.n} frames, RMS "
                   f"{registration.rms * 1e3:.4f} mm): x,y,z {', '.join(f'{a * 1e3:.3f}' for a in v[:3])} mm, "
                   f"rotation vector {', '.join(f'{np.degrees(a):.4f}' for a in v[3:])} deg")
    typer.echo(f"build {s['build_seconds'] * 1e3:.1f} ms; lookup {cost * 1e6:.2f} us per query (vectorised) -> {out}")


@map_app.command("apply")
def apply_command(
    model: str = typer.Option(..., "--model", help="Built-in model name or model file"),
    payload: str = PAYLOAD,
    map_file: Path = typer.Option(..., "--map", help="The map (station-map/1 JSON)"),
    poses: Path = typer.Option(..., "--poses", help="CSV of target poses (base frame)"),
    out: Path = typer.Option(..., "--out", help="CSV of actuator commands x1..xN, a status per row, and every "
                                                "column of --poses"),
    units: str = typer.Option(None, "--units", help="Output units LENGTH,ANGLE (default SI, plain headers)"),
) -> None:
    """Actuator commands that reach target poses, corrected by the map. Every row gets a command or a status
    naming why not; exit 1 when any row has none."""
    m = _model(model, payload)
    cmap = _load_map(map_file)
    t = _read(poses)
    target, cols = _pose(t, m, "targets")
    t0 = time.perf_counter()
    results, status = per_row(lambda rows: cmap.command(m, target[rows], cols), len(t.rows), t)
    dt = time.perf_counter() - t0
    u = _units(units)
    kinds = [j.revolute for j in m.joints]
    c = _stack(results, 0, m.n_joints)
    _write_rows(out, t, [_header(f"x{k + 1}", kinds[k], u) for k in range(m.n_joints)], c,
                np.array([u[2] if r else u[0] for r in kinds]), status)
    good = ~np.isnan(c[:, 0])
    line = f"apply: {int(good.sum())} of {len(c)} targets, {dt / len(c) * 1e6:.1f} us per target (IK + map)"
    if good.any():
        corr = np.max(np.abs(c[good] - _stack(results, 1, m.n_joints)[good]), axis=0)
        line += "; largest correction " + ", ".join(f"x{k + 1} {_human(v, kinds[k])}" for k, v in enumerate(corr))
    typer.echo(f"{line} -> {out}")
    _exit_failed(status, t, "target", "command", out)


@map_app.command("correct")
def correct_command(
    model: str = typer.Option(..., "--model", help="Built-in model name or model file"),
    payload: str = PAYLOAD,
    map_file: Path = typer.Option(..., "--map", help="The map (station-map/1 JSON)"),
    joints: Path = typer.Option(..., "--joints", help="CSV of actuator readings x1..xN"),
    out: Path = typer.Option(..., "--out", help="CSV of corrected poses, a status per row, and every column of "
                                                "--joints"),
    units: str = typer.Option(None, "--units", help="Output units LENGTH,ANGLE (default SI, plain headers)"),
) -> None:
    """Where the robot really is at actuator readings: the pose corrected by the map. Every row gets a pose or a
    status naming why not; exit 1 when any row has none."""
    from station.solver.map import output_columns

    m = _model(model, payload)
    cmap = _load_map(map_file)
    t = _read(joints)
    x = _actuators(t, m)
    from station.solver.map import MapError

    try:
        cols = output_columns(cmap.model_for(m))
    except MapError as e:  # a map of another model: nothing to do per row
        raise _fail(f"{map_file}: {e}") from None
    t0 = time.perf_counter()
    results, status = per_row(lambda rows: cmap.measure(m, x[rows]), len(t.rows), t)
    dt = time.perf_counter() - t0
    u = _units(units)
    pose = _stack(results, 0, len(cols))
    _write_rows(out, t, [_header(c, c.startswith("r"), u) for c in cols], pose,
                np.array([u[2] if c.startswith("r") else u[0] for c in cols]), status)
    typer.echo(f"correct: {int((~np.isnan(pose[:, 0])).sum())} of {len(pose)} readings, "
               f"{dt / len(pose) * 1e6:.1f} us per reading (map + DK) -> {out}")
    _exit_failed(status, t, "reading", "pose", out)


def per_row(fn, n: int, t: Table) -> tuple[list, list[str]]:
    """``fn(rows)`` on every row; a row it refuses (a ``MapError`` naming it) gets that reason as its status
    and the others are computed again without it. Returns, per row, the tuple of ``fn``'s arrays for that row
    (None where refused) and the statuses (``ok`` or why not). An error about no row (a map of another model)
    stays one line, exit 2."""
    from station.solver.map import MapError

    status = ["ok"] * n
    results: list = [None] * n
    rows = list(range(n))
    while rows:
        try:
            out = fn(np.array(rows))
        except MapError as e:
            i = getattr(e, "row", None)
            if i is None or not 0 <= i < len(rows):
                raise _row_error(e, t) from None
            status[rows[i]] = _reason(str(e))
            del rows[i]
            continue
        for k, r in enumerate(rows):
            results[r] = tuple(np.atleast_2d(a)[k] if isinstance(a, np.ndarray) else a for a in out)
        break
    return results, status


def _reason(message: str) -> str:
    """A MapError's message without its "target 3: " (the row is the row of the output file)."""
    return re.sub(r"^(target|reading|configuration|sample) \d+: ", "", " ".join(message.split()))


def _stack(results: list, k: int, width: int) -> np.ndarray:
    return np.array([r[k] if r is not None else np.full(width, np.nan) for r in results], float).reshape(-1, width)


def _write_rows(path: Path, t: Table, header: list[str], values: np.ndarray, scale: np.ndarray,
                status: list[str]) -> None:
    """The results, a ``status`` column, then every column of the input as it was written (a column whose
    name the output uses is kept as ``input_NAME``), and the input's comment lines: nothing of it is lost."""
    names = {h.split("[")[0].lower() for h in header} | {"status"}
    extra = sorted(t.columns.values(), key=lambda kc: kc[0])
    heads = [(f"input_{c.header}" if c.name in names else c.header) for _, c in extra]
    buf = io.StringIO()
    for line in _comments(Path(t.path)):
        buf.write(line + "\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*header, "status", *heads])
    for i, r in enumerate(np.atleast_2d(values)):
        cells = ["" if not np.isfinite(v) else f"{v / s:.15g}" for v, s in zip(r, scale, strict=True)]
        w.writerow([*cells, status[i], *(t.rows[i][k] for k, _ in extra)])
    _write_text(path, buf.getvalue())


def _comments(path: Path) -> list[str]:
    try:
        return [ln.rstrip("\r") for ln in path.read_text(errors="replace").splitlines() if ln.lstrip().startswith("#")]
    except OSError:
        return []


def _exit_failed(status: list[str], t: Table, what: str, result: str, out: Path) -> None:
    """Exit 1 naming how many rows got no result and why (the first few, with their input lines)."""
    import sys

    bad = [i for i, s in enumerate(status) if s != "ok"]
    if not bad:
        return
    typer.echo(f"station: {len(bad)} of {len(status)} {what}s have no {result} (status column of {out}):", err=True)
    for i in bad[:5]:
        typer.echo(f"  {t.where(i)}: {status[i]}", err=True)
    if len(bad) > 5:
        typer.echo(f"  ... and {len(bad) - 5} more", err=True)
    sys.exit(1)


def register(app: typer.Typer) -> None:
    app.add_typer(map_app, name="map")
