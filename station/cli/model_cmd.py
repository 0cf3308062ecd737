"""``station model list|show|export|import``: built-in models, model files and URDFs."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from station.cli import COMMANDS
from station.cli.helpgroup import HelpGroup
from station.cli.model_options import BASE_LINK, PAYLOAD, TIP_LINK, load_cli_model
from station.lazy import lazy_module

np = lazy_module("numpy")  # imported on first use (station.lazy: start-up of every command)

model_app = typer.Typer(cls=HelpGroup, no_args_is_help=True, help=COMMANDS["model"][1])
NAME = typer.Argument(..., help="Built-in model name, model file or URDF")
UNITS = typer.Option("mm,deg", help="Length and angle units: m or mm, rad or deg")


@model_app.command("list")
def list_models() -> None:
    """List the built-in models (name, joints, kind, description): what --model takes besides a file."""
    from station.kinematics import builtin_names, load_model

    rows = []
    for name in builtin_names():
        m = load_model(name)
        kind = "parallel" if getattr(m, "kind", "serial") == "parallel" else m.convention.upper()
        rows.append((name, f"{m.n_joints} joints", kind, m.description))
    w = [max(len(r[k]) for r in rows) for k in range(3)]
    for r in rows:
        typer.echo(f"{r[0]:{w[0]}s}  {r[1]:{w[1]}s}  {r[2]:{w[2]}s}  {r[3]}")


@model_app.command("show")
def show(name: str = NAME, units: str = UNITS, tip_link: str = TIP_LINK, base_link: str = BASE_LINK,
         payload: str = PAYLOAD) -> None:
    """Print a model: joints, limits, geometry table, masses and parameter names."""
    from station.kinematics import dump_model

    length, angle = _units(units)
    m = load_cli_model(name, tip_link, base_link, payload)
    typer.echo(dump_model(m, length, angle), nl=False)
    urdf = (getattr(m, "source", None) or {}).get("urdf")  # parallel models have no URDF source
    if urdf:
        typer.echo(f"# from URDF {urdf['path']}: chain {urdf['base_link']} -> {urdf['tip_link']} "
                   f"(joints {', '.join(j.name for j in m.joints)})")
        for joint, cal in urdf["calibration"].items():
            typer.echo(f"# URDF <calibration> of {joint}: " + ", ".join(f"{k}={v:g}" for k, v in cal.items()))
    typer.echo(f"# parameters ({len(m.param_names)}): " + ", ".join(m.param_names))
    typer.echo("# groups: " + "; ".join(f"{g}={','.join(v)}" for g, v in sorted(m.groups.items())))
    if getattr(m, "kind", "serial") == "parallel":  # q = 0 cannot be assembled: show the home configuration
        q = m.home_q
        typer.echo(f"# actuators at home (m): {np.round(q, 6).tolist()}")
        typer.echo(f"# tool position at home (m): {np.round(m.position(q), 6).tolist()}")
        return
    typer.echo(f"# tool position at q=0 (m): {np.round(m.position(np.zeros(m.n_joints)), 6).tolist()}")


@model_app.command("export")
def export(name: str = typer.Argument(None, help="Built-in model name, model file or URDF (default: the model of "
                                                 "the --calibration session or result)"),
           out: Path = typer.Option(None, "--out", "-o", help="File to write (default NAME.yaml / NAME.urdf)"),
           fmt: str = typer.Option(None, "--format", help="Format: yaml (station-model/1) or urdf (default: from the "
                                                          "--out suffix, else yaml)"),
           calibration: str = typer.Option(None, "--calibration", help="Write the calibrated robot: a session id, "
                                           "a session folder, a result JSON (station solve --out, a session's "
                                           "result.json) or a session's report.json"),
           units: str = UNITS, tip_link: str = TIP_LINK, base_link: str = BASE_LINK, payload: str = PAYLOAD) -> None:
    """Write a model file (or a URDF) of the nominal or calibrated robot; a model file can be edited and
    passed back as --model FILE."""
    from station.cli import fail
    from station.cli.calibration_source import calibration_source
    from station.kinematics import dump_model

    fmt = fmt or ("urdf" if out is not None and out.suffix.lower() == ".urdf" else "yaml")
    if fmt not in ("yaml", "urdf"):
        raise fail(f"--format {fmt!r}: expected yaml or urdf")
    length, angle = _units(units)
    source = calibration_source(calibration) if calibration is not None else None
    if name is None:
        if source is None or source.model is None:
            raise fail("model export: name the model (station model export ur5e ...), or give --calibration "
                       "SESSION, whose robot URL names it")
        name = source.model
        tip_link, base_link = tip_link or source.tip_link, base_link or source.base_link
    m = load_cli_model(name, tip_link, base_link, payload)
    note = ""
    if source is not None:
        m = source.apply(m)
        note = f"Calibrated: {source.what}."
    out = out or Path(f"{m.name}{'-calibrated' if source is not None else ''}.{fmt}")
    if Path(name).exists() and out.resolve() == Path(name).resolve():
        raise fail(f"--out {out}: that is the model being read; write somewhere else")
    if fmt == "urdf":
        from station.kinematics.urdfexport import urdf_text

        _write(out, urdf_text(m, note))
    else:
        _write(out, dump_model(m, length, angle))
    typer.echo(str(out))


@model_app.command("import")
def import_urdf(urdf: Path = typer.Argument(..., help="URDF file"),
                out: Path = typer.Option(None, "--out", "-o", help="Model file to write (default ROBOT.yaml)"),
                units: str = UNITS, tip_link: str = TIP_LINK, base_link: str = BASE_LINK) -> None:
    """Convert the chain of a URDF into a station-model/1 file (modified DH, masses from <inertial>)."""
    from station.kinematics import dump_model
    from station.kinematics.catalog import is_urdf
    from station.robot.errors import ConfigError

    if urdf.exists() and not is_urdf(urdf):
        raise ConfigError(f"{urdf}: not a URDF (expected XML with a <robot> root)")
    length, angle = _units(units)
    m = load_cli_model(str(urdf), tip_link, base_link)
    out = out or Path(f"{m.name}.yaml")
    _write(out, dump_model(m, length, angle))
    typer.echo(f"{out}: {m.name}, {m.n_joints} joints ({', '.join(j.name for j in m.joints)}), "
               f"{m.source['urdf']['base_link']} -> {m.source['urdf']['tip_link']}")


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _units(text: str) -> tuple[str, str]:
    from station.cli import fail

    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or parts[0] not in ("m", "mm") or parts[1] not in ("rad", "deg"):
        raise fail(f"--units {text!r}: expected LENGTH,ANGLE with m|mm and rad|deg")
    return parts[0], parts[1]


def register(app: typer.Typer) -> None:
    app.add_typer(model_app, name="model")
