"""The cell's schema: sql/*.sql applied in name order, in one transaction under an advisory lock;
the machines of etc/cell.toml registered; the lot scripts' connection limit set (gwc.budget); and the
cell's id counters (get_new_max_value)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import psycopg
from psycopg import sql

from gwc.budget import plan
from gwc.config import Config, shipped
from gwc.db.access import set_role_passwords
from gwc.db.connect import connect, one_line
from gwc.errors import DatabaseError

SQL_DIR = shipped("sql")
SCHEMA_TRIES = 3  # applications of the schema, when one ends in a deadlock with the running cell's reads
SCHEMA_PAUSE_S = 0.2  # s before the second try; twice that before the third
UNDONE = (psycopg.errors.DeadlockDetected, psycopg.errors.SerializationFailure)  # the server undid it all

_log = logging.getLogger("gwc.db")


def sql_files() -> list[Path]:
    return sorted(SQL_DIR.glob("*.sql"))


def init_schema(cfg: Config, log: logging.Logger | None = None) -> None:
    """Apply sql/*.sql in name order (all idempotent), then register the machines of cell.toml.

    One transaction under an advisory lock, so two processes initialising at once take turns and a
    failure leaves the database as it was. Machines in cell.toml that the seed does not know get a
    me_config row, a 'Shutdown' machine_status row and, by kind, the seed's recipes.

    Applied while the cell runs (`gwc db start` after the database was lost), its DDL's locks may meet
    a module's reads in a deadlock: the server undoes the whole transaction, and it is applied again
    (SCHEMA_TRIES in all).
    """
    log = log or _log
    files = sql_files()
    if not files:
        raise DatabaseError(f"no schema files in {SQL_DIR}: the checkout is incomplete")
    with connect(cfg, log=log) as conn:
        for attempt in range(1, SCHEMA_TRIES + 1):
            try:
                _apply(conn, cfg, files, log)
                break
            except UNDONE as e:  # a deadlock, undone whole: nothing half applied
                if attempt == SCHEMA_TRIES:
                    raise DatabaseError(f"applying the schema failed {attempt} times: {one_line(e)}") from e
                log.warning("applying the schema: %s: again (try %d of %d)", one_line(e), attempt + 1, SCHEMA_TRIES)
                time.sleep(SCHEMA_PAUSE_S * attempt)
            except psycopg.Error as e:
                raise DatabaseError(f"applying the schema failed: {one_line(e)}") from e
    log.info("schema applied (%s)", ", ".join(p.name for p in files))


def _apply(conn: psycopg.Connection[Any], cfg: Config, files: list[Path], log: logging.Logger) -> None:
    """One try of init_schema: every file, the machines, the roles' passwords and the lots' limit."""
    with conn.transaction(), conn.cursor() as cur:
        cur.execute("select pg_advisory_xact_lock(hashtext('gwc.init_schema'))")
        for path in files:
            log.debug("applying %s", path.name)
            try:
                cur.execute(path.read_text())
            except UNDONE:
                raise  # init_schema tries again
            except psycopg.Error as e:
                raise DatabaseError(f"{path.name}: {one_line(e)}") from e
        _register_machines(cur, cfg)
        if cfg.database_host is not None:
            set_role_passwords(cur, cfg)
        if cfg.embedded:
            limit_lot_connections(cur, cfg, log)


def limit_lot_connections(cur: psycopg.Cursor[Any], cfg: Config, log: logging.Logger) -> None:
    """Lot scripts log in as gwc_lot, whose connection limit is their share of the budget
    (gwc/budget.py): however many scripts run, on however many hosts, the modules and the operator
    keep theirs. The cell's own cluster only: a plant's server is its DBA's to size (docs/operating.md)."""
    budget = plan(cfg)
    cur.execute(sql.SQL("alter role gwc_lot login connection limit {}").format(sql.Literal(budget.lots)))
    log.info("database connections: %s", budget.describe())


# What a machine of each kind can do out of the box, as the seed gives the NJIT cell's machines.
KIND_RECIPES = {
    "cmm": [("alum_chess_set", "alum_chess")],
    "dummy": [("mill_pawn", "mill_chess"), ("dummy_recipe", "dummy_op"), ("dummy_recipe", "measure")],
}


def _register_machines(cur: psycopg.Cursor[Any], cfg: Config) -> None:
    for m in cfg.machines:
        cur.execute(
            "insert into me_config (machine_id, kind, liveness_s) values (%s, %s, %s) "
            "on conflict (machine_id) do update set kind = excluded.kind, liveness_s = excluded.liveness_s",
            (m.id, m.kind, m.liveness),
        )
        cur.execute(
            "insert into machine_status (machine_id, status) values (%s, 'Shutdown') on conflict do nothing", (m.id,)
        )
        for recipe_id, op_type in KIND_RECIPES.get(m.kind, []):
            cur.execute(
                "insert into op_machine_recipe (machine_id, recipe_id, op_type) "
                "select %s, %s, %s where exists (select 1 from recipes where recipe_id = %s) "
                "and exists (select 1 from op_types where op_type = %s) on conflict do nothing",
                (m.id, recipe_id, op_type, recipe_id, op_type),
            )


def get_new_max_value(cur_or_conn: psycopg.Cursor[Any] | psycopg.Connection[Any], type: str) -> int:
    """The next id of a kind (MACH_R_KEY, MACH_R_ID, ENTITY_ID, LOT_ID, WORK_ORDER, ALARM_NO).

    Strictly increasing per type and transactional: the counter row stays locked until the caller
    commits, so call it late in short transactions.
    """
    row = cur_or_conn.execute("select get_new_max_value(%s)", (type,)).fetchone()
    assert row is not None
    return int(row[0])
