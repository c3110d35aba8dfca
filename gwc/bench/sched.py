"""Placeholder: filled in by its issue."""

import click

from gwc.errors import GwcError


@click.command("sched")
def command() -> None:
    """Not built yet."""
    raise GwcError("gwc bench sched is not built yet")
