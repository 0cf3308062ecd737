"""The options ``station run`` and ``station panel`` share (the limits, the records database, the pose plan).
Use them as parameter defaults, as station/cli/model_options.py's are used. The plan's are the engine's
declarations (``station.engine.declare``: the flags ``station run`` builds for the procedures that plan poses)."""

from __future__ import annotations

import typer

from station.engine import declare

LIMITS = typer.Option(None, "--limits", help="Limits file (default: procedures/limits.yaml).")
DB = typer.Option(None, "--db", help="Records database URL (default $STATION_DB, else SQLite in $STATION_HOME).")
POSES = typer.Option(None, declare.POSES.flag, help=declare.POSES.doc + " Default: the procedure's.")
HOLDOUT = typer.Option(None, declare.HOLDOUT.flag, help=declare.HOLDOUT.doc)
CONE = typer.Option(None, declare.CONE.flag, help=declare.CONE.doc)
REFERENCE = typer.Option(None, declare.REFERENCE.flag, help=declare.REFERENCE.doc)
TOUCH = typer.Option(None, declare.TOUCH.flag, help=declare.TOUCH.doc)
