"""`gwc db cluster` and `gwc db switchover`: the replicated cell database under Patroni (gwc/patroni.py)."""

from __future__ import annotations

import json
from dataclasses import asdict

import click

from gwc import patroni
from gwc.client.session import context
from gwc.hi.cell import db_group


@db_group.command("cluster")
@click.option("--json", "as_json", is_flag=True, help="Print the members as JSON.")
def cluster(as_json: bool) -> None:
    """The Patroni cluster's members: who is the primary, the synchronous standby, each one's lag."""
    cfg, _ = context()
    members = patroni.members(cfg)
    if as_json:
        click.echo(json.dumps([asdict(m) for m in members], indent=1))
        return
    click.echo(f"{'MEMBER':10} {'ROLE':13} {'STATE':10} {'ADDRESS':22} {'TL':>3} {'LAG':>8}")
    for m in members:
        lag = "" if m.lag is None else str(m.lag)
        click.echo(
            f"{m.name:10} {m.role:13} {m.state:10} {m.host + ':' + str(m.port):22} {m.timeline or '':>3} {lag:>8}"
        )


@db_group.command("switchover")
@click.option("--to", "to", default=None, help="The member to become the primary (default: Patroni's choice).")
def switchover(to: str | None) -> None:
    """Hand the primary over to another member while the cell runs (Patroni's planned switchover)."""
    cfg, _ = context()
    click.echo(patroni.switchover(cfg, to))


commands: list[click.Command] = [db_group]  # `gwc db` (gwc/hi/cell.py), with the commands above
