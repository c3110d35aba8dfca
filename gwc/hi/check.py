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
@click.option(
    "--settle",
    type=float,
    default=3.0,
    show_default=True,
    help="Look again after this many seconds and report only what still breaches (0: one snapshot).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the breaches as JSON.")
def check(no_bus: bool, settle: float, as_json: bool) -> None:
    """Check the cell's invariants; exit 0 only when every one holds.

    No machine reserved by two entities or one run bound to two, no reservation or request of a
    missing or finished entity, no request waiting for a shut-down machine, no bound request still
    queued, no run with results from two machines, no lot neither finished, failed nor progressing
    (its script dead, or waiting with nothing queued), and (unless --no-bus) no status row that
    contradicts the live WCs and no configured server down. A running cell always has something in
    flight, so a breach must hold in two snapshots --settle seconds apart to be reported.
    """
    cfg, log = context()
    with db.connect(cfg, role="hi", log=log) as conn:
        conn.autocommit = True  # only reads: each sees the cell as it is now
        if no_bus:
            breaches = check_cell(cfg, conn, None, settle)
        else:
            with hi_bus(cfg, log) as bus:
                breaches = check_cell(cfg, conn, bus, settle)
    if as_json:
        click.echo(json.dumps([b.as_dict() for b in breaches], default=str, indent=1))
    else:
        for b in breaches:
            click.echo(f"BREACH {b.invariant}: {b.promise}")
            for row in b.rows[:20]:
                click.echo("  " + ", ".join(f"{k}={v}" for k, v in row.items()))
            if len(b.rows) > 20:
                click.echo(f"  ... and {len(b.rows) - 20} more")
        if not breaches:
            click.echo("all invariants hold")
    if breaches:
        log.warning("gwc check: %d invariant(s) breached: %s", len(breaches), ", ".join(b.invariant for b in breaches))
        raise click.exceptions.Exit(1)


commands = [check]
