"""MSCHED's screen (MREQ, thesis 6.2.3 and Listing 8): the request queue, the reservations, cancel.

`gwc requests` reads the tables (anyone may read), filtered by lot, machine, entity and op type as the
screen's fields (Figure 6.8), `--zoom KEY` one request in detail; `gwc cancel` and `gwc unreserve` ask
MSCHED over the bus, since only MSCHED writes its tables (gwc.client.requests holds them).
"""

from __future__ import annotations

import json
from typing import Any

import click

from gwc.client.record import record_action
from gwc.client.requests import RequestFilter, cancel_request, request_tables, unreserve_machine, zoom_request
from gwc.client.session import hi_bus, hi_conn, operator
from gwc.errors import GwcError
from gwc.hi import context, table


@click.command("requests")
@click.option("--lot", default=None, help="Only this lot id (shell wildcards: 1*, ?2).")
@click.option("--machine", default=None, help="Only requests naming this machine, and its reservation (wc*).")
@click.option("--entity", default=None, help="Only this entity id (wildcards).")
@click.option("--op", default=None, help="Only this op type (wildcards: mill_*); reservations keep no op type.")
@click.option("--zoom", "zoom", type=int, default=None, metavar="KEY", help="One waiting request in detail.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON for scripts instead of tables.")
def requests(
    lot: str | None, machine: str | None, entity: str | None, op: str | None, zoom: int | None, as_json: bool
) -> None:
    """The machine request queue (oldest first), the reserved machines, and answers not yet acknowledged:
    MREQ's screen (Figure 6.8), filtered by lot, machine, entity and op type as its fields are."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        if zoom is not None:
            detail = zoom_request(conn, zoom)
            if detail is None:
                raise GwcError(f"request {zoom} is not waiting (see `gwc requests`)")
            return show_zoom(detail, as_json)
        queue, reserved, telling = request_tables(conn, RequestFilter(lot, machine, entity, op))
    if as_json:
        table([{"requests": queue, "reserved": reserved, "telling": telling}], [], as_json=True)
        return
    click.echo(f"Requests waiting ({len(queue)}):")
    table(queue, ["request_key", "lot_id", "entity_id", "op_type", "machines", "priority", "since"])
    click.echo(f"\nReserved machines ({len(reserved)}):")
    table(reserved, ["machine_id", "lot_id", "entity_id", "entity_state", "machine_run_id", "request_key", "since"])
    if telling:
        click.echo(f"\nAnswers not yet acknowledged ({len(telling)}):")
        table(telling, ["request_key", "lot_id", "entity_id", "ack_code", "machines", "state", "note"])


def show_zoom(detail: dict[str, Any], as_json: bool) -> None:
    """MREQ's Zoom: the request, its entity and lot, each machine and its status."""
    if as_json:
        click.echo(json.dumps(detail, default=str, indent=1))
        return
    for k, v in detail.items():
        if k != "machines":
            click.echo(f"{k:>13}: {'-' if v is None else v}")
    click.echo("     machines:")
    for m in detail["machines"]:
        run = f" (run {m['machine_run_id']})" if m["machine_run_id"] is not None else ""
        click.echo(f"               {m['machine_id']}: {m['status'] or 'unknown'}{run}")


@click.command("unreserve")
@click.argument("machine_id")
@click.option("--force", is_flag=True, help="Even while the holder's lot script runs.")
def unreserve(machine_id: str, force: bool) -> None:
    """Free a machine held by a lot entity whose script died and will not come back (6.2.4.7)."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        entity = unreserve_machine(cfg, bus, machine_id, force)
    click.echo(f"{machine_id} freed (it was reserved to entity {entity}); MSCHED may give it to the next request")


@click.command("cancel")
@click.argument("request_key", type=int, required=False)
@click.option("--entity", "entity_id", type=int, help="Cancel every request of this entity instead.")
def cancel(request_key: int | None, entity_id: int | None) -> None:
    """Cancel a waiting machine request (Listing 8): MSCHED tells its entity REQ_CANCEL."""
    if (request_key is None) == (entity_id is None):
        raise click.UsageError("give a REQUEST_KEY or --entity ENTITY_ID (one of them)")
    cfg, log = context()
    what = f"request {request_key}" if request_key is not None else f"the requests of entity {entity_id}"
    whose = entity_id
    if whose is None:  # the entity whose request it is: its history records the cancel
        with hi_conn(cfg, log) as conn:
            row = conn.execute(
                "select entity_id from request_machines where request_key = %s", (request_key,)
            ).fetchone()
        whose = row[0] if row else None
    with hi_bus(cfg, log) as bus:
        ack = cancel_request(bus, request_key, entity_id, by=operator())
        if whose is not None and cfg.record.history:
            try:
                record_action(bus, whose, "cancel", operator(), f"{ack.cancelled} request(s): {what}")
            except GwcError as e:
                click.echo(f"gwc: the cancel is not in entity {whose}'s history: {e}", err=True)
    click.echo(f"cancelled {ack.cancelled} request(s) ({what}); the entity was told REQ_CANCEL")


commands = [requests, cancel, unreserve]
