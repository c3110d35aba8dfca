"""MSCHED's screen (MREQ, thesis 6.2.3 and Listing 8): the request queue, the reservations, cancel.

`gwc requests` reads the tables (anyone may read); `gwc cancel` asks MSCHED over the bus, since only
MSCHED writes its tables (gwc.client.requests holds both).
"""

from __future__ import annotations

import click

from gwc.client.record import record_action
from gwc.client.requests import cancel_request, request_tables
from gwc.client.session import hi_bus, hi_conn, operator
from gwc.errors import GwcError
from gwc.hi import context, table


@click.command("requests")
@click.option("--json", "as_json", is_flag=True, help="Print JSON for scripts instead of tables.")
def requests(as_json: bool) -> None:
    """The machine request queue (oldest first), the reserved machines, and answers not yet acknowledged."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        queue, reserved, telling = request_tables(conn)
    if as_json:
        table([{"requests": queue, "reserved": reserved, "telling": telling}], [], as_json=True)
        return
    click.echo(f"Requests waiting ({len(queue)}):")
    table(queue, ["request_key", "entity_id", "op_type", "machines", "priority", "since"])
    click.echo(f"\nReserved machines ({len(reserved)}):")
    table(reserved, ["machine_id", "entity_id", "machine_run_id", "request_key", "since"])
    if telling:
        click.echo(f"\nAnswers not yet acknowledged ({len(telling)}):")
        table(telling, ["request_key", "entity_id", "ack_code", "machines", "state", "note"])


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


commands = [requests, cancel]
