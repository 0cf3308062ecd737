"""``python -m station.cli`` runs the ``station`` command."""

from station.cli import main

main()
