"""``station model list|show|export``: built-in kinematic models."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from station.kinematics import builtin_names, dump_model, load_model

model_app = typer.Typer(no_args_is_help=True, help="Built-in kinematic models (show, export).")


@model_app.command("list")
def list_models() -> None:
    """List built-in models."""
    for name in builtin_names():
        m = load_model(name)
        typer.echo(f"{name:8s} {m.n_joints} joints  {m.convention.upper():4s} {m.description}")


@model_app.command("show")
def show(name: str, units: str = typer.Option("mm,deg", help="length,angle units: m|mm, rad|deg")) -> None:
    """Print a model: joints, limits, geometry table and parameter names."""
    length, angle = _units(units)
    m = load_model(name)
    typer.echo(dump_model(m, length, angle), nl=False)
    typer.echo(f"# parameters ({len(m.param_names)}): " + ", ".join(m.param_names))
    typer.echo("# groups: " + "; ".join(f"{g}={','.join(v)}" for g, v in sorted(m.groups.items())))
    if getattr(m, "kind", "serial") == "parallel":  # q = 0 cannot be assembled: show the home configuration
        q = m.home_q
        typer.echo(f"# actuators at home (m): {np.round(q, 6).tolist()}")
        typer.echo(f"# tool position at home (m): {np.round(m.position(q), 6).tolist()}")
        return
    typer.echo(f"# tool position at q=0 (m): {np.round(m.position(np.zeros(m.n_joints)), 6).tolist()}")


@model_app.command("export")
def export(name: str, out: Path = typer.Option(None, "--out", "-o", help="file to write (default NAME.yaml)"),
           units: str = typer.Option("mm,deg", help="length,angle units: m|mm, rad|deg")) -> None:
    """Write a model file that can be edited and passed back as --model FILE."""
    length, angle = _units(units)
    m = load_model(name)
    out = out or Path(f"{m.name}.yaml")
    out.write_text(dump_model(m, length, angle))
    typer.echo(str(out))


def _units(text: str) -> tuple[str, str]:
    from station.cli import fail

    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or parts[0] not in ("m", "mm") or parts[1] not in ("rad", "deg"):
        raise fail(f"--units {text!r}: expected LENGTH,ANGLE with m|mm and rad|deg")
    return parts[0], parts[1]


def register(app: typer.Typer) -> None:
    app.add_typer(model_app, name="model")
