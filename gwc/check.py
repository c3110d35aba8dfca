"""The cell's invariants, checked against the database and (optionally) the live bus.

`gwc check` exits 0 only when every invariant holds. Each database invariant is one query returning
the rows that breach it, so adding a promise is adding one entry to INVARIANTS. The live checks
compare the status rows with what the modules themselves announce on the bus (their hellos carry
the classes they listen to, which tells a started module from one waiting for STARTUP).

A cell that runs is never frozen: a lot script between its unreserve and its `completed`, a WC
between its status change and its new interest, are breaches for a few milliseconds. `settle`
takes a second snapshot after that many seconds and reports only what breached in both, so a
check of a live cell names what is really wrong, not what was in flight.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from typing import Any

import psycopg

from gwc.config import Config
from gwc.ipc import BlockingBus, Peer
from gwc.ipc.codes import LotState, MachineStatus
from gwc.ipc.names import Conv

# An entity in one of these states will never ask for a machine again.
FINISHED = (LotState.COMPLETED.value, LotState.WAITING_EXPORT.value, LotState.EXPORTED.value, LotState.FAILED.value)
# A machine in one of these states is started: its WC serves SETUP_RUN.
STARTED = (MachineStatus.IDLE.value, MachineStatus.SETUP.value, MachineStatus.RUNNING.value)
# An entity waiting for a machine with nothing queued, or holding machines none of which has run
# anything, for this long is stuck (what it waits for can never come): far longer than any step
# between a lot script's conversations takes.
STALE_S = 10


@dataclass(frozen=True)
class Invariant:
    name: str
    promise: str
    sql: str


INVARIANTS = (
    Invariant(
        "double_reservation",
        "a machine is reserved by at most one entity",
        "SELECT machine_id, array_agg(DISTINCT entity_id ORDER BY entity_id) AS entities FROM reserved_machines "
        "GROUP BY machine_id HAVING count(DISTINCT entity_id) > 1",
    ),
    Invariant(
        "run_id_shared",
        "a machine_run_id is bound to one entity",
        "SELECT machine_run_id, array_agg(DISTINCT entity_id ORDER BY entity_id) AS entities FROM reserved_machines "
        "GROUP BY machine_run_id HAVING count(DISTINCT entity_id) > 1",
    ),
    Invariant(
        "orphan_reservation",
        "every reservation belongs to a live, unfinished entity",
        "SELECT r.machine_id, r.entity_id, s.state FROM reserved_machines r "
        "LEFT JOIN lot_entities e ON e.entity_id = r.entity_id LEFT JOIN lot_status s ON s.entity_id = r.entity_id "
        f"WHERE e.entity_id IS NULL OR e.destroyed_at IS NOT NULL OR s.state IS NULL OR s.state IN {FINISHED}",
    ),
    Invariant(
        "orphan_request",
        "every queued request belongs to a live, unfinished entity",
        "SELECT q.request_key, q.machine_id, q.entity_id, s.state FROM request_machines q "
        "LEFT JOIN lot_entities e ON e.entity_id = q.entity_id LEFT JOIN lot_status s ON s.entity_id = q.entity_id "
        f"WHERE e.entity_id IS NULL OR e.destroyed_at IS NOT NULL OR s.state IS NULL OR s.state IN {FINISHED}",
    ),
    Invariant(
        "request_on_shutdown_machine",
        "no queued request waits for a machine that is shut down",
        "SELECT q.request_key, q.machine_id, q.entity_id FROM request_machines q "
        "JOIN machine_status m USING (machine_id) WHERE m.status = 'Shutdown'",
    ),
    Invariant(
        "satisfied_request_queued",
        "a request that was bound is no longer queued",
        "SELECT DISTINCT q.request_key, q.entity_id FROM request_machines q "
        "JOIN reserved_machines r ON r.request_key = q.request_key",
    ),
    Invariant(
        "setup_not_reserved",
        "a machine set up for a run is reserved for it (or gives the setup up within seconds)",
        "SELECT m.machine_id, m.machine_run_id, m.updated_at FROM machine_status m "
        f"WHERE m.status IN ('Setup', 'Setup_Shut') AND m.updated_at < now() - interval '{3 * STALE_S} seconds' "
        "AND NOT EXISTS (SELECT 1 FROM reserved_machines r WHERE r.machine_id = m.machine_id "
        "AND r.machine_run_id = m.machine_run_id)",
    ),
    Invariant(
        "run_on_two_machines",
        "a machine_run_id has results from one machine",
        "SELECT machine_run_id, array_agg(DISTINCT machine_id ORDER BY machine_id) AS machines "
        "FROM machine_run_result GROUP BY machine_run_id HAVING count(DISTINCT machine_id) > 1",
    ),
    Invariant(
        "waiting_without_request",
        "an entity waiting for a machine has a request queued or a machine bound",
        "SELECT s.entity_id, s.lot_id, s.state, s.updated_at FROM lot_status s "
        "WHERE s.state = 'waiting_machine' "
        f"AND s.updated_at < now() - interval '{STALE_S} seconds' "
        "AND NOT EXISTS (SELECT 1 FROM request_machines q WHERE q.entity_id = s.entity_id) "
        "AND NOT EXISTS (SELECT 1 FROM reserved_machines r WHERE r.entity_id = s.entity_id)",
    ),
    Invariant(
        "run_lost",
        "an entity at work on its machines has a run going on at least one of them",
        "SELECT r.entity_id, array_agg(r.machine_id ORDER BY r.machine_id) AS machines, "
        "array_agg(m.status ORDER BY r.machine_id) AS statuses FROM reserved_machines r "
        "JOIN lot_status s USING (entity_id) JOIN machine_status m USING (machine_id) "
        "WHERE s.state = 'running' GROUP BY r.entity_id "
        "HAVING bool_and(m.status NOT IN ('Setup', 'Running', 'Setup_Shut', 'Run_Shut') "
        f"AND m.updated_at < now() - interval '{STALE_S} seconds' "
        f"AND r.reserved_at < now() - interval '{STALE_S} seconds')",
    ),
)

# Unfinished entities and their scripts: stuck unless the script lives (checked in Python).
_UNFINISHED = (
    "SELECT s.entity_id, s.lot_id, s.state, s.script_pid FROM lot_status s "
    f"WHERE s.state NOT IN {FINISHED} AND (s.state <> 'created' OR s.script_pid IS NOT NULL)"
)


@dataclass(frozen=True)
class Breach:
    invariant: str
    promise: str
    rows: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"invariant": self.invariant, "promise": self.promise, "rows": self.rows}


def pid_alive(pid: int) -> bool:
    """Whether pid is a running (not zombie) process on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _rows(conn: psycopg.Connection[Any], sql: str) -> list[dict[str, Any]]:
    cur = conn.execute(sql)
    cols = [d.name for d in cur.description or []]
    return [dict(zip(cols, r)) for r in cur.fetchall()]


def check_database(conn: psycopg.Connection[Any], peers: dict[str, Peer] | None = None) -> list[Breach]:
    """Every database invariant; with `peers` (the bus's members), a script on the bus counts as alive."""
    breaches = []
    for inv in INVARIANTS:
        rows = _rows(conn, inv.sql)
        if rows:
            breaches.append(Breach(inv.name, inv.promise, rows))
    stuck = []
    for row in _rows(conn, _UNFINISHED):
        on_bus = peers is not None and f"lot:{row['entity_id']}" in peers
        alive = row["script_pid"] is not None and pid_alive(row["script_pid"])
        if not (on_bus or alive):
            stuck.append(row)
    if stuck:
        breaches.append(Breach("stuck_lot", "every lot entity is finished, failed, or has a living lot script", stuck))
    return breaches


def check_live(cfg: Config, conn: psycopg.Connection[Any], peers: dict[str, Peer]) -> list[Breach]:
    """Status rows that contradict the live modules, and configured servers that are not up."""
    breaches = []
    status = {mid: st for mid, st in conn.execute("SELECT machine_id, status FROM machine_status")}
    missing, disagree = [], []
    for mid, st in sorted(status.items()):
        peer = peers.get(f"wc:{mid}")
        if peer is None:
            if st != MachineStatus.SHUTDOWN:
                missing.append({"machine_id": mid, "status": st})
            continue
        wc_started = Conv.SETUP_RUN in peer.interest
        if wc_started != (st in STARTED):
            disagree.append({"machine_id": mid, "status": st, "wc": "started" if wc_started else "not started"})
    if missing:
        breaches.append(Breach("status_without_wc", "a machine that is not Shutdown has its WC on the bus", missing))
    if disagree:
        breaches.append(Breach("status_contradicts_wc", "a machine's status row agrees with its WC", disagree))
    down = []
    for m in cfg.modules:
        peer = peers.get(m.name)
        if peer is None or Conv.SHUTDOWN not in peer.interest:
            down.append({"module": m.name, "state": "absent" if peer is None else "not started"})
    if down:
        breaches.append(Breach("module_down", "every configured server is on the bus and started", down))
    return breaches


def _snapshot(cfg: Config, conn: psycopg.Connection[Any], bus: BlockingBus | None) -> list[Breach]:
    if bus is None:
        return check_database(conn)
    peers = bus.peers()
    return check_database(conn, peers) + check_live(cfg, conn, peers)


def _row_key(row: dict[str, Any]) -> str:
    return json.dumps(row, sort_keys=True, default=str)


def persistent(first: list[Breach], second: list[Breach]) -> list[Breach]:
    """The breach rows present in both snapshots (as they read in the second)."""
    before = {(b.invariant, _row_key(r)) for b in first for r in b.rows}
    kept = []
    for b in second:
        rows = [r for r in b.rows if (b.invariant, _row_key(r)) in before]
        if rows:
            kept.append(Breach(b.invariant, b.promise, rows))
    return kept


def check_cell(
    cfg: Config, conn: psycopg.Connection[Any], bus: BlockingBus | None, settle: float = 0.0
) -> list[Breach]:
    """Every invariant; with `settle` > 0, only breaches that still hold `settle` seconds later.

    Reads only. Give it an autocommit (or READ COMMITTED) connection, so each query sees the
    cell as it is now rather than as it was when a transaction began.

    With a bus, waits one peer_timeout first so every live module has said hello (a membership
    window, not a wait for a condition).
    """
    if bus is not None:
        time.sleep(cfg.bus.peer_timeout)
    breaches = _snapshot(cfg, conn, bus)
    if breaches and settle > 0:
        time.sleep(settle)
        breaches = persistent(breaches, _snapshot(cfg, conn, bus))
    return breaches
