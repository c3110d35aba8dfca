"""No module writes another's tables (thesis 5.1): each server acts as its own database role, and the
grants let that role write its own tables and nothing else, so a server that tried would fail."""

from __future__ import annotations

import importlib
from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.errors import DatabaseError
from gwc.module import BUS_MODULES

# The servers' tables (GUIDE 4, docs/servers.md). me_config and op_types are configuration the
# seed writes; the Machine Server and the ERS keep them as well.
OWNED = {
    "ms": {"machine_status", "me_config", "scrap_reports", "machine_state_history", "downtime_events"},
    "ls": {"lots", "lot_entities", "lot_status", "entity_state_history", "operator_actions"},
    "cas": {"alarms", "alarm_description"},
    "ers": {"recipes", "recipe_versions", "op_machine_recipe", "op_types"},
    "sls": set(),
    "opcua": set(),
}
# Tables every door appends to and nobody changes (sql/090_users.sql: insert only, a trigger refuses the rest).
APPEND_ONLY = {"audit_trail": {"hi", "opcua"}}
ROLES = ["msched", "ms", "ls", "cas", "ers", "sls", "wc", "hi", "lot", "opcua"]
# One row each server could plausibly write into another's table.
TRY = {
    "machine_status": "update machine_status set note = 'x' where machine_id = 'wc1'",
    "lots": "update lots set owner = 'x'",
    "lot_status": "update lot_status set reason = 'x'",
    "alarms": "update alarms set cleared_by = 'x', cleared_at = now()",
    "recipe_versions": "update recipe_versions set approved = false",
    "request_machines": "delete from request_machines",
    "reserved_machines": "delete from reserved_machines",
    "machine_run_result": "delete from machine_run_result",
    "machine_run_outcome": "delete from machine_run_outcome",
}


def _writers(conn: psycopg.Connection[Any]) -> dict[str, set[str]]:
    rows = conn.execute(
        "select c.relname, r.rolname from pg_class c cross join pg_roles r "
        "where c.relkind = 'r' and c.relnamespace = 'public'::regnamespace and r.rolname = any(%s) "
        "and (has_table_privilege(r.oid, c.oid, 'INSERT') or has_table_privilege(r.oid, c.oid, 'UPDATE') "
        "or has_table_privilege(r.oid, c.oid, 'DELETE'))",
        ([f"gwc_{r}" for r in ROLES],),
    ).fetchall()
    out: dict[str, set[str]] = {}
    for table, role in rows:
        out.setdefault(table, set()).add(role.removeprefix("gwc_"))
    return out


def test_each_server_runs_as_its_own_role() -> None:
    for name in OWNED:
        mod, _, cls = BUS_MODULES[name].partition(":")
        assert getattr(importlib.import_module(mod), cls).role == name


def test_every_table_has_at_most_one_writer_and_each_server_writes_exactly_its_own(
    db_conn: psycopg.Connection[Any],
) -> None:
    writers = _writers(db_conn)
    for table, doors in APPEND_ONLY.items():
        assert writers.pop(table) == doors, table
    shared = {t: w for t, w in writers.items() if len(w) > 1}
    assert not shared, f"tables with more than one writer: {shared}"
    for server, tables in OWNED.items():
        assert {t for t, w in writers.items() if server in w} == tables, server


@pytest.mark.parametrize("server", sorted(OWNED))
def test_a_server_role_cannot_write_another_modules_table(cell_config: Config, server: str) -> None:
    conn = db.connect(cell_config, role=server)
    try:
        for table, sql in TRY.items():
            if table in OWNED[server]:
                continue
            with pytest.raises(DatabaseError, match="permission denied"):
                db.transaction(conn, lambda cur, s=sql: cur.execute(s))
        # and reading stays free: the status line reads the Lot Server's and the CAS's tables
        assert db.transaction(conn, lambda cur: cur.execute("select count(*) from lot_status").fetchone())
    finally:
        conn.close()
