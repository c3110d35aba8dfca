"""Placeholder: filled in by its issue."""

import click

from gwc.errors import GwcError


@click.command("cell")
def command() -> None:
    """Not built yet."""
    raise GwcError("gwc bench cell is not built yet")
