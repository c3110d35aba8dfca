"""MSCHED's screen (MREQ, thesis 6.2.3 and Listing 8): the request queue, the reservations, cancel.

`gwc requests` reads the tables (anyone may read); `gwc cancel` asks MSCHED over the bus, since only
MSCHED writes its tables.
"""

from __future__ import annotations

from typing import Any

import click
import psycopg

from gwc import db
from gwc.cell import hi_bus
from gwc.errors import GwcError, Refused
from gwc.hi import context, table
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode

CANCEL_TIMEOUT = 10.0

_QUEUE = """
select q.request_key, q.entity_id, q.op_type, string_agg(q.machine_id, ' AND ' order by q.seq) as machines,
       min(q.priority) as priority, min(q.seq) as seq, to_char(min(q.requested_at), 'YYYY-MM-DD HH24:MI:SS') as since,
       min(q.reply_to) as reply_to
from request_machines q group by q.request_key, q.entity_id, q.op_type order by min(q.seq)
"""
_RESERVED = """
select machine_id, entity_id, machine_run_id, request_key, to_char(reserved_at, 'YYYY-MM-DD HH24:MI:SS') as since
from reserved_machines order by machine_id
"""
_TELLING = """
select request_key, entity_id, ack_code, array_to_string(machines, ' AND ') as machines, machine_run_id,
       case when held then 'held: entity has a live alternative' else 'waiting for Request_Comp_Ack' end as state,
       note
from request_outcomes order by decided_at, request_key
"""


def _rows(cur: Any, sql: str) -> list[dict[str, Any]]:
    cur.execute(sql)
    cols = [d.name for d in cur.description or []]
    return [dict(zip(cols, r)) for r in cur.fetchall()]


def request_tables(conn: psycopg.Connection[Any]) -> tuple[list[dict[str, Any]], ...]:
    """MREQ's three tables: the requests waiting, the reserved machines, the answers not yet acknowledged."""
    with conn.cursor() as cur:
        tables = tuple(_rows(cur, q) for q in (_QUEUE, _RESERVED, _TELLING))
    conn.rollback()
    return tables


def cancel_request(bus: BlockingBus, request_key: int | None, entity_id: int | None, by: str) -> Message:
    """CANCEL_RE to MSCHED (one request, or every request of an entity); returns its Cancel_Req_Ack."""
    conv, batch = bus.request(
        "CANCEL_RE",
        message("Cancel_Request", request_key=request_key, entity_id=entity_id, by=by),
        to="msched",
        timeout=CANCEL_TIMEOUT,
    )
    conv.end()
    return batch.first


@click.command("requests")
@click.option("--json", "as_json", is_flag=True, help="Print JSON for scripts instead of tables.")
def requests(as_json: bool) -> None:
    """The machine request queue (oldest first), the reserved machines, and answers not yet acknowledged."""
    cfg, log = context()
    with db.connect(cfg, role="hi", log=log) as conn:
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
    with hi_bus(cfg, log) as bus:
        ack = cancel_request(bus, request_key, entity_id, f"hi.{cfg.cell_name}")
    if ack.ack_code == AckCode.REQ_KEY_U:
        raise GwcError(f"nothing waiting to cancel for {what} (REQ_KEY_U): see `gwc requests`")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"MSCHED did not cancel {what}")
    click.echo(f"cancelled {ack.cancelled} request(s) ({what}); the entity was told REQ_CANCEL")


commands = [requests, cancel]
