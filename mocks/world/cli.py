"""``station mock world example|show|cell``: write, inspect and export simulated worlds."""

from __future__ import annotations

from pathlib import Path

import typer

world_app = typer.Typer(no_args_is_help=True, help="Simulated world: robot with hidden errors, cell, faults.")


def _fail(message: str) -> Exception:
    # station.cli.main prints "station: error: ..." and exits 2
    from station.mocks.errors import MockError

    return MockError(message)


def _load(path: Path):
    from station.mocks.world import World, WorldFileError

    try:
        return World.from_file(path)
    except WorldFileError as e:
        raise _fail(str(e)) from None


@world_app.command("example")
def example(model: str = typer.Option("ur5e", "--model", help="Built-in model name, model file or URDF (an arm of "
                                                              "one's own gets a cell computed for it)."),
            seed: int = typer.Option(0, "--seed", help="Seed written into the file."),
            tip_link: str = typer.Option(None, "--tip-link", help="URDF: the link at the end of the chain (default: "
                                         "the end of the only longest chain)."),
            base_link: str = typer.Option(None, "--base-link", help="URDF: the link the chain starts from (default: "
                                          "the root).")) -> None:
    """Print a complete, commented world file (mm, deg): station mock world example > world.yaml"""
    from station.mocks.world.example import example_text

    from station.kinematics import ModelFileError

    try:
        typer.echo(example_text(model, seed, tip_link, base_link), nl=False)
    except ModelFileError as e:
        raise _fail(str(e)) from None


@world_app.command("show")
def show(file: Path = typer.Argument(..., help="World file (station-world/1)."),
         length: str = typer.Option("mm", "--length", help="Length unit of the report: mm or m."),
         angle: str = typer.Option("deg", "--angle", help="Angle unit of the report: deg or rad.")) -> None:
    """Print the hidden truth: every perturbed parameter (nominal, true, difference), the cell points."""
    if length not in ("mm", "m") or angle not in ("deg", "rad"):
        raise _fail(f"--length must be mm or m and --angle deg or rad (got {length!r}, {angle!r})")
    typer.echo(_load(file).truth_report(length, angle))


@world_app.command("cell")
def cell(file: Path = typer.Argument(..., help="World file (station-world/1)."),
         out: Path | None = typer.Option(None, "--out", help="Write the station-cell/1 file here (default: stdout).")
         ) -> None:
    """Export the station-side cell file (approximate point positions as an integrator knows them)."""
    import yaml

    world = _load(file)
    doc = world.station_cell()
    text = ("# station cell (station-cell/1): reference points in the robot base frame, lengths in m, unit\n"
            "# approach vectors point from the point towards the tool. Positions are surveyed, not exact.\n"
            + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    if _emit(text, out):
        typer.echo(f"wrote {out} ({len(doc['points'])} points)", err=True)
    for line in cell_warnings(world, file):
        typer.echo(line, err=True)


def cell_warnings(world, file: Path) -> list[str]:
    """What a procedure would refuse later, said now: a cell without points, a point the nominal arm cannot
    reach from the plan's cone inside its limits with its links clear of the floor and the world's keep-outs."""
    if getattr(world.nominal, "kind", "serial") == "parallel":
        return []  # measured by a tracker: no touch points needed
    if not world.points:
        return [f"station: warning: {file}: cell.points is empty: no procedure can touch anything; reachable "
                f"points for this arm are in the cell.points of: station mock world example --model "
                f"{_model_ref(world)}"]
    import numpy as np
    from station.mocks.world.reach import MIN_SCORE, cone_scores

    from station.kinematics.collision import keep_out_from_dict

    keep_out = keep_out_from_dict(world.station_cell(), str(file), 1.0, 1.0)  # the station's, 10 mm clearance
    pts = list(world.points.values())
    scores, _ = cone_scores(world.nominal, np.array([p.position for p in pts]), keep_out)
    out = []
    for p, sc in zip(pts, scores, strict=True):
        if sc < MIN_SCORE:
            out.append(f"station: warning: {file}: cell.points {p.label} at {np.round(p.position * 1e3).tolist()} mm: "
                       f"the nominal {world.nominal.name} reaches it from {sc:.0%} of a 35 deg cone of tool directions "
                       "clear of the floor and keep-outs; move it (station mock world example --model ... computes "
                       "reachable points)")
    return out


@world_app.command("freeze")
def freeze(file: Path = typer.Argument(..., help="World file (station-world/1)."),
           out: Path | None = typer.Option(None, "--out", help="Output file (default: stdout).")) -> None:
    """Rewrite a world with its random errors drawn and written out explicitly (mm, deg)."""
    import yaml

    text = ("# station simulated world (station-world/1), random errors frozen; lengths mm, angles deg\n"
            + yaml.safe_dump(_load(file).to_dict("mm", "deg", frozen=True), sort_keys=False,
                           default_flow_style=None))
    _emit(text, out)


def _model_ref(world) -> str:
    urdf = (getattr(world.nominal, "source", None) or {}).get("urdf") or {}
    return str(urdf.get("path") or world.spec.model)


def _emit(text: str, out: Path | None) -> bool:
    """Print ``text``, or write it to ``out`` (True when written); a write error is one line, exit 2."""
    if out is None:
        typer.echo(text, nl=False)
        return False
    try:
        out.write_text(text)
    except OSError as e:
        raise _fail(f"{out}: cannot write ({e.strerror})") from None
    return True


def register(mock_app: typer.Typer) -> None:
    mock_app.add_typer(world_app, name="world")
