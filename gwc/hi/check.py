"""`gwc check`: are the cell's promises kept?"""

from __future__ import annotations

import json

import click

from gwc import db
from gwc.cell import hi_bus
from gwc.check import check_cell
from gwc.hi import context


@click.command("check")
@click.option("--no-bus", is_flag=True, help="Check the database only, not the live modules on the bus.")
@click.option("--json", "as_json", is_flag=True, help="Print the breaches as JSON.")
def check(no_bus: bool, as_json: bool) -> None:
    """Check the cell's invariants; exit 0 only when every one holds.

    No machine reserved twice, no reservation or request of a dead or finished entity, no request
    waiting for a shut-down machine, no run with results from two machines, no lot stuck with a
    dead script, and (unless --no-bus) no machine up whose WC is absent from the bus.
    """
    cfg, log = context()
    with db.connect(cfg, log=log) as conn:
        if no_bus:
            breaches = check_cell(cfg, conn, None)
        else:
            with hi_bus(cfg, log) as bus:
                breaches = check_cell(cfg, conn, bus)
    if as_json:
        click.echo(json.dumps([b.__dict__ for b in breaches], default=str, indent=1))
    else:
        for b in breaches:
            click.echo(f"BREACH {b.invariant}: {b.promise}")
            for row in b.rows[:20]:
                click.echo("  " + ", ".join(f"{k}={v}" for k, v in row.items()))
        if not breaches:
            click.echo("all invariants hold")
    if breaches:
        raise click.exceptions.Exit(1)


commands = [check]
