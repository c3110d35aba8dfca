"""`gwc host`: what the cell needs of its host's operating system, made by root once (bin/setup)."""

from __future__ import annotations

import click

from gwc.hostuser import CELL_USER, LOT_USER, ensure_users


@click.group("host")
def host_group() -> None:
    """The host's side of the cell: its OS users (docs/security.md, who runs as whom)."""


@host_group.command("users")
@click.option("--cell", "cell_user", default=CELL_USER, show_default=True, help="The cell's OS user.")
@click.option("--lot", "lot_user", default=LOT_USER, show_default=True, help="The lot scripts' OS user.")
def users(cell_user: str, lot_user: str) -> None:
    """Make the cell's and the lot scripts' system users (root; safe to run again)."""
    made = ensure_users(cell_user, lot_user)
    click.echo(f"made: {', '.join(made)}" if made else f"users {cell_user} and {lot_user}: already there")


commands = [host_group]
