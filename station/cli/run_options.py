"""The options ``station run`` and ``station panel`` share (the limits, the records database, the pose plan).
Use them as parameter defaults, as station/cli/model_options.py's are used."""

from __future__ import annotations

import typer

LIMITS = typer.Option(None, "--limits", help="Limits file (default: procedures/limits.yaml).")
DB = typer.Option(None, "--db", help="Records database URL (default $STATION_DB, else SQLite in $STATION_HOME).")
POSES = typer.Option(None, "--poses", help="Number of fit poses (default from the procedure).")
HOLDOUT = typer.Option(None, "--holdout", help="Number of held-out poses.")
CONE = typer.Option(None, "--cone", help="Half-angle of the cone of tool directions around each point, an angle: "
                    "50deg, 0.87rad (a bare number is degrees).")
