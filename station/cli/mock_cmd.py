"""Placeholder: this command group is being built (see the open issues); it registers nothing yet."""

import typer


def register(app: typer.Typer) -> None:
    return None
