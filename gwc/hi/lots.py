"""`gwc lots divide|merge|destroy`: the Lot Server's division, merger and destruction of entities (1.4.4),
beside `gwc lots [ENTITY]`, the Dispatch List (gwc/hi/orders.py), which stays what `gwc lots` with
anything else runs. The conversations are gwc.client.lots'."""

from __future__ import annotations

from typing import Any

import click

from gwc.client.lots import destroy_entity, divide_entity, merge_entities
from gwc.client.orders import list_lots, spawn_lot_scripts
from gwc.client.session import hi_bus, need_server
from gwc.hi import context
from gwc.hi.orders import lots as dispatch_list


class LotsGroup(click.Group):
    """`gwc lots` is the Dispatch List unless its first word is one of the subcommands."""

    def resolve_command(
        self, ctx: click.Context, args: list[str]
    ) -> tuple[str | None, click.Command | None, list[str]]:
        if args and args[0] in self.commands:
            return super().resolve_command(ctx, args)
        return "lots", dispatch_list, args


@click.group(
    "lots",
    cls=LotsGroup,
    invoke_without_command=True,
    context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
    help=(dispatch_list.help or "")
    + "\n\nThe list takes [ENTITY] [--order N] [--state S] [--json]."
    + "\n\nAlso: `gwc lots divide E`, `gwc lots merge E OTHER`, `gwc lots destroy E` (the Lot Server's rules: "
    "docs/servers.md).",
)
@click.pass_context
def lots(ctx: click.Context) -> None:
    if ctx.invoked_subcommand is None:
        ctx.invoke(dispatch_list)


@lots.command("divide")
@click.argument("entity", type=int)
@click.option("--quantity", type=int, default=1, show_default=True, help="How many new entities to split off.")
@click.option("--no-scripts", is_flag=True, help="Start no lot scripts for the new entities.")
def lots_divide(entity: int, quantity: int, no_scripts: bool) -> None:
    """Split new entities off a created or imported one: its lot, its state, it their parent. Their lot
    scripts are started (as an order's are) when the divided entity's is running."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        need_server(bus, "ls", "Lot Server")
        new = divide_entity(bus, entity, quantity)
    click.echo(f"entity {entity} divided: new entities {', '.join(map(str, new))}")
    running = any(r["script"] not in ("-",) and "ended" not in r["script"] for r in list_lots(cfg, log, entity=entity))
    if new and running and not no_scripts:
        pids: dict[int, Any] = spawn_lot_scripts(cfg, new)
        click.echo("lot scripts started: " + ", ".join(f"{e} (pid {p or 'queued'})" for e, p in pids.items()))


@lots.command("merge")
@click.argument("entity", type=int)
@click.argument("other", type=int)
def lots_merge(entity: int, other: int) -> None:
    """Fold OTHER into ENTITY (OTHER is destroyed): both created or imported, of one lot and one state."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        need_server(bus, "ls", "Lot Server")
        merge_entities(bus, entity, other)
    click.echo(f"entity {other} merged into {entity}")


@lots.command("destroy")
@click.argument("entity", type=int)
def lots_destroy(entity: int) -> None:
    """Destroy an entity that is created, exported or failed: it leaves the lists (its history stays)."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        need_server(bus, "ls", "Lot Server")
        destroy_entity(bus, entity)
    click.echo(f"entity {entity} destroyed")


commands = [lots]
