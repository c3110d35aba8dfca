"""Placeholder: filled in by its issue."""

import click

from gwc.errors import GwcError


@click.command("mq")
def command() -> None:
    """Not built yet."""
    raise GwcError("gwc bench mq is not built yet")
