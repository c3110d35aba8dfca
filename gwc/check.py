"""The cell's invariants, checked against the database and (optionally) the live bus.

`gwc check` exits 0 only when every invariant holds. Each invariant is one query returning the rows
that breach it, so adding a promise is adding one entry to INVARIANTS.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc.config import Config
from gwc.ipc.bus import BlockingBus

FINISHED = ("completed", "waiting_export", "exported", "failed")


@dataclass(frozen=True)
class Invariant:
    name: str
    promise: str
    sql: str


INVARIANTS = (
    Invariant(
        "double_reservation",
        "a machine is reserved by at most one entity",
        "SELECT machine_id, count(DISTINCT entity_id) AS entities FROM reserved_machines "
        "GROUP BY machine_id HAVING count(DISTINCT entity_id) > 1",
    ),
    Invariant(
        "orphan_reservation",
        "every reservation belongs to a live, unfinished entity",
        "SELECT r.machine_id, r.entity_id, s.state FROM reserved_machines r "
        "LEFT JOIN lot_entities e ON e.entity_id = r.entity_id LEFT JOIN lot_status s ON s.entity_id = r.entity_id "
        f"WHERE e.entity_id IS NULL OR e.destroyed_at IS NOT NULL OR s.state IN {FINISHED}",
    ),
    Invariant(
        "orphan_request",
        "every queued request belongs to a live, unfinished entity",
        "SELECT q.request_key, q.entity_id, s.state FROM request_machines q "
        "LEFT JOIN lot_entities e ON e.entity_id = q.entity_id LEFT JOIN lot_status s ON s.entity_id = q.entity_id "
        f"WHERE e.entity_id IS NULL OR e.destroyed_at IS NOT NULL OR s.state IN {FINISHED}",
    ),
    Invariant(
        "request_on_shutdown_machine",
        "no queued request waits for a machine that is shut down",
        "SELECT q.request_key, q.machine_id FROM request_machines q JOIN machine_status m USING (machine_id) "
        "WHERE m.status = 'Shutdown'",
    ),
    Invariant(
        "reserved_and_queued",
        "an entity holding machines has no request still queued",
        "SELECT DISTINCT q.entity_id, q.request_key FROM request_machines q "
        "JOIN reserved_machines r ON r.entity_id = q.entity_id",
    ),
    Invariant(
        "run_on_two_machines",
        "a machine_run_id has results from one machine",
        "SELECT machine_run_id, count(DISTINCT machine_id) AS machines FROM machine_run_result "
        "GROUP BY machine_run_id HAVING count(DISTINCT machine_id) > 1",
    ),
    Invariant(
        "stuck_lot",
        "every lot entity is finished, failed, or has a living lot script",
        "SELECT entity_id, state, script_pid FROM lot_status "
        "WHERE state NOT IN ('exported', 'failed', 'created') AND script_pid IS NOT NULL",
    ),
)


@dataclass(frozen=True)
class Breach:
    invariant: str
    promise: str
    rows: list[dict[str, Any]]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie has exited
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def check_database(conn: psycopg.Connection) -> list[Breach]:
    breaches = []
    for inv in INVARIANTS:
        cur = conn.execute(inv.sql)
        cols = [d.name for d in cur.description or []]
        rows = [dict(zip(cols, r)) for r in cur.fetchall()]
        if inv.name == "stuck_lot":
            rows = [r for r in rows if not _pid_alive(r["script_pid"])]
        if rows:
            breaches.append(Breach(inv.name, inv.promise, rows))
    return breaches


def check_live(conn: psycopg.Connection, bus: BlockingBus, listen: float) -> list[Breach]:
    """Status rows that contradict the live modules: a machine up whose WC is not on the bus."""
    time.sleep(listen)  # a membership window, not a wait for a condition: every live module says hello in it
    peers = bus.peers()
    rows = [
        {"machine_id": mid, "status": status}
        for mid, status in conn.execute("SELECT machine_id, status FROM machine_status WHERE status <> 'Shutdown'")
        if f"wc:{mid}" not in peers
    ]
    return [Breach("status_without_wc", "a machine that is up has its WC on the bus", rows)] if rows else []


def check_cell(cfg: Config, conn: psycopg.Connection, bus: BlockingBus | None) -> list[Breach]:
    breaches = check_database(conn)
    if bus is not None:
        breaches += check_live(conn, bus, cfg.bus.peer_timeout)
    return breaches
