"""``station compensate --model M --calibration R --poses TARGETS.csv --out COMMANDS.csv``: the commands that
bring a calibrated robot onto its targets through a controller that keeps its own nominal model
(docs/iso9283.md, "Compensated targets"; the correction map's analogue is ``station map apply``).

``--calibration``: a ``station solve`` result JSON, a session (id, folder or journal: its solve result) or a
session's ``report.json`` (with its journal beside it: the session; alone: the parameters' standard deviations,
no correlations). ``--poses``: ``x,y,z`` and optionally ``rx,ry,rz`` (rotation vector) per row, base frame, units
in the headers (``x[mm]``, ``rx[deg]``); other columns ignored (a ``name`` column is carried over). Out: per row
``status``, the joint commands ``q1..qN`` (default) or, with ``--cartesian``, the corrected targets, then the
predicted residual and its uncertainty (1 sigma, from the calibration's covariance) and the correction. Exit 1
(naming them) when targets are unreachable: their rows say why, every other row is written."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import typer

from station.cli.model_options import BASE_LINK, MODEL, PAYLOAD, TIP_LINK
from station.lazy import lazy_module
from station.robot.errors import ConfigError

np = lazy_module("numpy")


def _units(text: str | None) -> tuple[float, str, float, str]:
    from station.units import ANGLE_UNITS, LENGTH_UNITS

    if text is None or text.strip().lower() in ("si", "m,rad"):
        return 1.0, "m", 1.0, "rad"
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or parts[0] not in LENGTH_UNITS or parts[1] not in ANGLE_UNITS:
        raise ConfigError(f"--units {text!r}: expected LENGTH,ANGLE (m|mm|cm|um, rad|deg|mrad) or SI")
    return LENGTH_UNITS[parts[0]], parts[0], ANGLE_UNITS[parts[1]], parts[1]


def load_result(ref: str, model):
    """The calibration ``--calibration REF`` names (``station.cli.calibration_source``, the one reader: a result
    JSON, a session, a report) as a ``CalibrationResult`` checked against ``model``, where it came from, and
    what it was solved from (its samples: a session's journal, a result's ``settings.samples``), if known."""
    from station.cli.calibration_source import calibration_source

    src = calibration_source(ref)
    res = src.calibration_result(model)
    design = None
    if src.samples:
        smp = src.samples
        measured = all(x.get("measured") is not None for x in smp)
        design = _design(res, np.array([x["q"] for x in smp], float),
                         np.array([x.get("point", "A") for x in smp], dtype=object), measured)
    elif src.file is not None:
        design = _design_from_file(res, model, src.file)
    return res, src.what, design


def _design(res, q, labels, measured: bool):
    """What the calibration was solved from (``station.performance.compensate.Design``), or None when its noise
    or priors are not in the result."""
    from station.performance.compensate import Design

    sigma = (res.noise or {}).get("sigma_m") or res.sigma_m
    priors = {n: p.prior_std for n, p in res.parameters.items() if p.kind == "model" and p.prior_std}
    if not sigma or not priors:
        return None
    ref = (res.settings or {}).get("reference")
    known = tuple(ref) if isinstance(ref, dict) else ()
    frame_known = (res.settings or {}).get("instrument_frame") == "base"
    return Design(q, labels, measured, frame_known, float(sigma), priors, known)


def _design_from_file(res, model, path: Path):
    """The samples a ``station solve`` result names (``settings.samples``), if that file is still there."""
    from station.samplesfile import SamplesFileError, read_samples

    name = (res.settings or {}).get("samples")
    if not name:
        return None
    p = Path(name) if Path(name).is_absolute() else (path.parent / name if not Path(name).exists() else Path(name))
    try:
        smp = read_samples(p, model)
    except (SamplesFileError, OSError):
        return None
    return _design(res, smp.q, smp.point, smp.measured is not None)


def read_targets(path: Path) -> tuple[np.ndarray, list[str] | None, object]:
    """Targets ``(N, 3)`` or ``(N, 6)`` (SI) and the ``name`` column if any."""
    from station.samplesfile import SamplesFileError, column_si, read_table

    try:
        t = read_table(path)
        for c in ("x", "y", "z"):
            if c not in t.columns:
                raise ConfigError(f"{t.path}:{t.header_line}: missing column {c!r} (targets: x, y, z and optionally "
                                  "rx, ry, rz)")
        rot = [c for c in ("rx", "ry", "rz") if c in t.columns]
        if rot and len(rot) != 3:
            miss = next(c for c in ("rx", "ry", "rz") if c not in t.columns)
            raise ConfigError(f"{t.path}:{t.header_line}: missing column {miss!r} (a rotation vector needs rx, ry, rz)")
        if not t.rows:
            raise ConfigError(f"{t.path}: no data rows")
        cols = [column_si(t, c, "length") for c in ("x", "y", "z")] + [column_si(t, c, "angle") for c in rot]
    except SamplesFileError as e:
        raise ConfigError(str(e)) from None
    names = [row[t.columns["name"][0]] for row in t.rows] if "name" in t.columns else None
    return np.column_stack(cols), names, t


def _start(text: str | None, model):
    if text is None:
        return None
    from station.units import ANGLE_UNITS, LENGTH_UNITS

    body, unit = text.strip(), ""
    while body and body[-1].isalpha():
        body, unit = body[:-1], body[-1] + unit
    try:
        v = [float(x) for x in body.split(",")]
    except ValueError:
        v = []
    if len(v) != model.n_joints or (unit and unit not in ANGLE_UNITS):
        raise ConfigError(f"--start {text!r}: expected {model.n_joints} joint values (rad, or one angle unit for all: "
                          "0,-90,90,-90,-90,0deg; prismatic joints in m, or mm with deg)")
    f = ANGLE_UNITS.get(unit or "rad", 1.0)
    lf = LENGTH_UNITS["mm"] if unit == "deg" else 1.0
    return np.array([x * (f if j.revolute else lf) for x, j in zip(v, model.joints, strict=True)])


def _uncertainty(res, cal, design) -> tuple:
    """``(covariance, its parameter names, parameters kept at their prior {name: (std, why)}, how it was
    obtained)`` for the predicted uncertainty of each compensated target."""
    if design is not None:  # the calibration's own samples: the parameters weighed again, aliasing included
        from station.performance.compensate import predictive_covariance

        cov, names_ = predictive_covariance(cal, design)
        return cov, names_, None, f"posterior of its {len(design.q)} samples"
    # the parameters' reported (consider) covariance: conservative
    kept = {n: (p.prior_std, p.cause or "weak") for n, p in res.parameters.items()
            if p.kind == "model" and not p.identifiable and p.prior_std}
    return res.covariance, res.identified, kept, "reported parameter covariance (its samples not found: conservative)"


def _commands_csv(m, source: str, comp, n_targets: int, names, u, cartesian: bool, how: str) -> str:
    """The text of the commands CSV: one row per target, its status, the command (empty when
    not reached) in the output units, residual, uncertainty and correction."""
    header = ["row", *(["name"] if names else []), "status"]
    if cartesian:
        header += [f"{c}[{u[3] if c.startswith('r') else u[1]}]" for c in ("x", "y", "z", "rx", "ry", "rz")]
        scale = [u[0]] * 3 + [u[2]] * 3
        values = comp.cartesian
    else:
        header += [f"q{k + 1}[{u[3] if j.revolute else u[1]}]" for k, j in enumerate(m.joints)]
        scale = [u[2] if j.revolute else u[0] for j in m.joints]
        values = comp.q
    header += [f"residual[{u[1]}]", f"residual_rotation[{u[3]}]", f"sigma[{u[1]}]", f"sigma_rotation[{u[3]}]",
               f"correction[{u[1]}]"]
    buf = io.StringIO()
    buf.write(f"# station compensate: model {m.name}, calibration {source}; "
              f"{'corrected Cartesian targets (rotation vector)' if cartesian else 'joint commands'} for the "
              f"controller's nominal model; residual and sigma (1 sigma, 3-D RMS) as the calibration predicts them, "
              f"sigma from the calibration's {how}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for i in range(n_targets):
        row = [i + 1, *([names[i]] if names else []), comp.status[i]]
        ok = comp.status[i] == "ok"
        row += [f"{v / s:.12g}" if ok else "" for v, s in zip(values[i], scale, strict=True)]
        extra = (comp.residual[i] / u[0], comp.residual_rotation[i] / u[2], comp.sigma[i] / u[0],
                 comp.sigma_rotation[i] / u[2], comp.correction[i] / u[0])
        row += ["" if not np.isfinite(v) else f"{v:.6g}" for v in extra]
        w.writerow(row)
    return buf.getvalue()


def _report(comp, n_targets: int, out: Path, urscript: Path | None, how: str, table) -> None:
    """One line for the operator; the unreachable rows on stderr, exit 1 when there are any."""
    good = int(comp.ok.sum())
    typer.echo(f"compensate: {good} of {n_targets} targets -> {out}"
               + (f" (+ URScript {urscript})" if urscript is not None else "")
               + (f"; largest correction {np.nanmax(comp.correction) * 1e3:.4f} mm, predicted uncertainty up to "
                  f"{np.nanmax(comp.sigma) * 1e3:.4f} mm (1 sigma, from the calibration's {how})" if good else ""))
    bad = [i for i, s in enumerate(comp.status) if s != "ok"]
    if bad:
        listed = "; ".join(f"row {i + 1} ({table.where(i)}): {comp.status[i]}" for i in bad[:5])
        more = f"; and {len(bad) - 5} more" if len(bad) > 5 else ""
        typer.echo(f"station: {len(bad)} of {n_targets} targets unreachable: {listed}{more}", err=True)
        raise typer.Exit(1)


def compensate_command(
    model: str = MODEL,
    tip_link: str = TIP_LINK,
    base_link: str = BASE_LINK,
    payload: str = PAYLOAD,
    tool: str = typer.Option(None, "--tool", help="Nominal TCP x,y,z in the flange frame (m, or suffix mm), before "
                             "the calibration (as for station solve)"),
    calibration: str = typer.Option(..., "--calibration", help="Result JSON of station solve, a session (id, folder "
                                    "or journal) or its report.json"),
    poses: Path = typer.Option(..., "--poses", help="CSV of targets x,y,z[,rx,ry,rz] in the base frame (units in "
                               "headers)"),
    out: Path = typer.Option(..., "--out", help="CSV of commands, one row per target, with status, residual, "
                             "uncertainty"),
    cartesian: bool = typer.Option(False, "--cartesian", help="Corrected Cartesian targets (x,y,z,rx,ry,rz) for a "
                                   "controller that takes Cartesian moves, instead of joint commands"),
    start: str = typer.Option(None, "--start", help="Joint values the first target is solved from (the robot's "
                              "configuration), e.g. 0,-90,90,-90,-90,0deg; default: near the middle of the ranges"),
    units: str = typer.Option(None, "--units", help="Output units LENGTH,ANGLE, e.g. mm,deg (default SI)"),
    urscript: Path = typer.Option(None, "--urscript", help="Also write a URScript program: one movej per reached "
                                  "target (6-axis models)"),
) -> None:
    """Compensated targets: joint (or corrected Cartesian) commands that a controller with its nominal model turns
    into the calibrated pose.

    Per row: the status, the predicted residual, its uncertainty and the correction."""
    from station.cli.solve_cmd import _load_model
    from station.performance.compensate import compensate
    from station.performance.compensate import urscript as ur_program
    from station.safeio import check_destination, write_atomic

    inputs = {"--poses": poses, "--calibration": Path(calibration)}
    check_destination(out, inputs)
    if urscript is not None:
        check_destination(urscript, inputs, "--urscript")
    m = _load_model(model, tool, tip_link, base_link, payload)
    if urscript is not None and m.n_joints != 6:
        raise ConfigError(f"--urscript: model {m.name} has {m.n_joints} joints; a UR program moves 6")
    res, source, design = load_result(calibration, m)
    if not res.trusted:
        raise ConfigError(f"calibration {source}: the result is not trusted ({res.failure or 'see the solve'})")
    try:
        cal = res.calibrated(m)
    except ValueError as e:
        raise ConfigError(f"calibration {source}: {e}") from None
    target, names, table = read_targets(poses)
    u = _units(units)
    q0 = _start(start, m)
    cov, names_, kept, how = _uncertainty(res, cal, design)
    comp = compensate(m, cal, target, covariance=cov, names=names_, kept=kept, start=q0)
    text = _commands_csv(m, source, comp, len(target), names, u, cartesian, how)
    write_atomic(out, text, inputs)
    if urscript is not None:
        write_atomic(urscript, ur_program(comp.q, comp.status, header=f"station compensate: model {m.name}, "
                                          f"calibration {Path(source).name}; joint targets in rad"), inputs)
    _report(comp, len(target), out, urscript, how, table)


def register(app: typer.Typer) -> None:
    app.command("compensate")(compensate_command)
