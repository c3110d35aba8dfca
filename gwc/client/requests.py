"""MSCHED's screen (MREQ, thesis 6.2.3, Listing 8): its request queue, reservations and answers not yet
acknowledged (read: anyone may), and CANCEL_RE (asked of MSCHED: only it writes its tables)."""

from __future__ import annotations

from typing import Any

import psycopg

from gwc.client.session import ANSWER, ask
from gwc.errors import GwcError, Refused
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg

QUEUE_SQL = """
select q.request_key, q.entity_id, q.op_type, string_agg(q.machine_id, ' AND ' order by q.seq) as machines,
       min(q.priority) as priority, min(q.seq) as seq, to_char(min(q.requested_at), 'YYYY-MM-DD HH24:MI:SS') as since,
       min(q.reply_to) as reply_to
from request_machines q group by q.request_key, q.entity_id, q.op_type order by min(q.seq)
"""
RESERVED_SQL = """
select machine_id, entity_id, machine_run_id, request_key, to_char(reserved_at, 'YYYY-MM-DD HH24:MI:SS') as since
from reserved_machines order by machine_id
"""
TELLING_SQL = """
select request_key, entity_id, ack_code, array_to_string(machines, ' AND ') as machines, machine_run_id,
       case when held then 'held: entity has a live alternative' else 'waiting for Request_Comp_Ack' end as state,
       note
from request_outcomes order by decided_at, request_key
"""

__all__ = ["cancel_request", "request_tables"]


def _rows(cur: Any, sql: str) -> list[dict[str, Any]]:
    cur.execute(sql)
    cols = [d.name for d in cur.description or []]
    return [dict(zip(cols, r)) for r in cur.fetchall()]


def request_tables(conn: psycopg.Connection[Any]) -> tuple[list[dict[str, Any]], ...]:
    """MREQ's three tables: the requests waiting (oldest first), the reserved machines, MSCHED's answers
    not yet acknowledged. On the caller's connection (a screen keeps one open)."""
    with conn.cursor() as cur:
        tables = tuple(_rows(cur, q) for q in (QUEUE_SQL, RESERVED_SQL, TELLING_SQL))
    conn.rollback()
    return tables


def cancel_request(
    bus: BlockingBus, request_key: int | None, entity_id: int | None, by: str, timeout: float = ANSWER
) -> Message:
    """CANCEL_RE to MSCHED: one waiting request, or every request of an entity (MSCHED tells the entity
    REQ_CANCEL). Returns its Cancel_Req_Ack (`cancelled`: how many); GwcError when nothing waited,
    Refused if MSCHED says no."""
    what = f"request {request_key}" if request_key is not None else f"the requests of entity {entity_id}"
    ack = ask(
        bus,
        Conv.CANCEL_RE,
        message(Msg.CANCEL_REQUEST, request_key=request_key, entity_id=entity_id, by=by),
        "msched",
        timeout,
    )
    if ack.ack_code == AckCode.REQ_KEY_U:
        raise GwcError(f"nothing waiting to cancel for {what} (REQ_KEY_U): see `gwc requests`")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"MSCHED did not cancel {what}")
    return ack
