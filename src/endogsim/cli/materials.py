"""CLI commands of this capability (filled in as it lands)."""

import typer


def register(app: typer.Typer) -> None:
    """Add this module's commands to ``app``."""
