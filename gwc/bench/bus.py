"""Placeholder: filled in by its issue."""

import click

from gwc.errors import GwcError


@click.command("bus")
def command() -> None:
    """Not built yet."""
    raise GwcError("gwc bench bus is not built yet")
