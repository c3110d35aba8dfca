"""MSCHED's screen (MREQ, thesis 6.2.3, Listing 8): its request queue, reservations and answers not yet
acknowledged (read: anyone may), and CANCEL_RE (asked of MSCHED: only it writes its tables)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc.cell import read_pid
from gwc.client.session import ANSWER, ask, hi_conn, operator
from gwc.config import Config
from gwc.errors import GwcError, Refused
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg

# Listing 8's screen filters the requests by Lot, Machine, Entity and Op type, "X" for any: here each is
# a pattern with shell wildcards (* any run, ? one character), None for any. A request matches on
# machines when one of its machines does; a reservation keeps no op type, so --op leaves them all.
QUEUE_SQL = """
select q.request_key, s.lot_id, q.entity_id, q.op_type, string_agg(q.machine_id, ' AND ' order by q.seq) as machines,
       min(q.priority) as priority, min(q.seq) as seq, to_char(min(q.requested_at), 'YYYY-MM-DD HH24:MI:SS') as since,
       min(q.reply_to) as reply_to
from request_machines q left join lot_status s using (entity_id)
group by q.request_key, s.lot_id, q.entity_id, q.op_type
having (%(lot)s::text is null or s.lot_id::text like %(lot)s)
   and (%(ent)s::text is null or q.entity_id::text like %(ent)s)
   and (%(op)s::text is null or q.op_type like %(op)s) and (%(m)s::text is null or bool_or(q.machine_id like %(m)s))
order by min(q.seq)
"""
RESERVED_SQL = """
select r.machine_id, s.lot_id, r.entity_id, r.machine_run_id, r.request_key,
       to_char(r.reserved_at, 'YYYY-MM-DD HH24:MI:SS') as since, s.state as entity_state
from reserved_machines r left join lot_status s using (entity_id)
where (%(lot)s::text is null or s.lot_id::text like %(lot)s)
  and (%(ent)s::text is null or r.entity_id::text like %(ent)s)
  and (%(m)s::text is null or r.machine_id like %(m)s)
order by r.machine_id
"""
TELLING_SQL = """
select o.request_key, s.lot_id, o.entity_id, o.ack_code, array_to_string(o.machines, ' AND ') as machines,
       o.machine_run_id,
       case when o.held then 'held: entity has a live alternative' else 'waiting for Request_Comp_Ack' end as state,
       o.note
from request_outcomes o left join lot_status s using (entity_id)
where (%(lot)s::text is null or s.lot_id::text like %(lot)s)
  and (%(ent)s::text is null or o.entity_id::text like %(ent)s)
  and (%(op)s::text is null or o.op_type like %(op)s)
  and (%(m)s::text is null or exists (select 1 from unnest(o.machines) x where x like %(m)s))
order by o.decided_at, o.request_key
"""
ZOOM_SQL = """
select q.machine_id, m.status as machine_status, m.machine_run_id as machine_run, q.op_type, q.priority,
       to_char(q.requested_at, 'YYYY-MM-DD HH24:MI:SS') as since, q.entity_id, q.reply_to, s.lot_id, s.state,
       s.script_pid, l.product_id, l.work_order_id, l.owner,
       (select count(distinct o.request_key) from request_machines o where o.seq < (select min(seq)
          from request_machines where request_key = q.request_key)) as ahead,
       (select string_agg(distinct a.request_key::text, ', ') from request_machines a
          where a.entity_id = q.entity_id and a.request_key <> q.request_key) as alternatives
from request_machines q left join machine_status m using (machine_id) left join lot_status s using (entity_id)
     left join lots l on l.lot_id = s.lot_id
where q.request_key = %s order by q.seq
"""

__all__ = ["RequestFilter", "cancel_request", "request_tables", "unreserve_machine", "zoom_request"]


@dataclass(frozen=True)
class RequestFilter:
    """The MREQ screen's fields (Figure 6.8): Lot, Machine, Entity, Op type; shell wildcards; None = any."""

    lot: str | None = None
    machine: str | None = None
    entity: str | None = None
    op: str | None = None

    def params(self) -> dict[str, str | None]:
        return {"lot": like(self.lot), "m": like(self.machine), "ent": like(self.entity), "op": like(self.op)}


def like(pattern: str | None) -> str | None:
    """A shell wildcard pattern (* and ?) as a LIKE pattern; None (and "*", "X": the screen's "any") as None."""
    if pattern is None or pattern in ("*", "X", "x"):
        return None
    escaped = pattern.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
    return escaped.replace("*", "%").replace("?", "_")


def _rows(cur: Any, sql: str, params: Any = None) -> list[dict[str, Any]]:
    cur.execute(sql, params)
    cols = [d.name for d in cur.description or []]
    return [dict(zip(cols, r)) for r in cur.fetchall()]


def request_tables(
    conn: psycopg.Connection[Any], where: RequestFilter | None = None
) -> tuple[list[dict[str, Any]], ...]:
    """MREQ's three tables: the requests waiting (oldest first), the reserved machines, MSCHED's answers
    not yet acknowledged, each filtered (`where`). On the caller's connection (a screen keeps one open)."""
    params = (where or RequestFilter()).params()
    with conn.cursor() as cur:
        tables = tuple(_rows(cur, q, params) for q in (QUEUE_SQL, RESERVED_SQL, TELLING_SQL))
    conn.rollback()
    return tables


def zoom_request(conn: psycopg.Connection[Any], request_key: int) -> dict[str, Any] | None:
    """MREQ's Zoom: one waiting request in detail (its entity and lot, each machine and its status, how
    many requests are ahead of it, the entity's other requests); None if it is not waiting."""
    with conn.cursor() as cur:
        rows = _rows(cur, ZOOM_SQL, (request_key,))
    conn.rollback()
    if not rows:
        return None
    first = rows[0]
    out: dict[str, Any] = {"request_key": request_key}
    out.update({k: first[k] for k in first if k not in ("machine_id", "machine_status", "machine_run")})
    out["machines"] = [
        {"machine_id": r["machine_id"], "status": r["machine_status"], "machine_run_id": r["machine_run"]} for r in rows
    ]
    return out


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


def unreserve_machine(
    cfg: Config, bus: BlockingBus, machine_id: str, force: bool = False, timeout: float = ANSWER, by: str | None = None
) -> int:
    """The operator's Unreserve_Machine (6.2.4.7): free a machine whose lot entity crashed, so that the
    scheduler does not keep it for an entity that no longer exists. UNRESERVE to MSCHED in the holder's
    name. Refused (GwcError) while the holder's lot script runs (on the bus, or its pid alive), unless
    `force`: a live script would find its machine gone mid-run. Returns the entity that held it.
    `by`: who acts, as recorded (the HI's operator unless said: the OPC UA gateway says itself)."""
    with hi_conn(cfg, logging.getLogger("gwc.hi")) as conn:
        row = conn.execute("select entity_id from reserved_machines where machine_id = %s", (machine_id,)).fetchone()
        conn.rollback()
    if row is None:
        raise GwcError(f"{machine_id} is not reserved (see `gwc requests`)")
    entity = int(row[0])
    if not force:
        pid = read_pid(cfg, f"lot:{entity}")
        if f"lot:{entity}" in bus.bus.peers() or pid.alive:
            raise GwcError(
                f"{machine_id} is held by entity {entity}, whose lot script runs"
                + (f" (pid {pid.pid})" if pid.alive else " (on the bus)")
                + ": it frees it itself; stop it first, or --force"
            )
    ack = ask(
        bus,
        Conv.UNRESERVE,
        message(Msg.UNRESERVE_ME, entity_id=entity, machine_id=machine_id, by=by or operator()),
        "msched",
        timeout,
    )
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"MSCHED did not free {machine_id}")
    return entity
