"""``python -m station.cli`` runs the ``station`` command (as the console script does)."""

from station.cli import console

console()
