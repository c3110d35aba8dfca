"""Schema versions (gwc/schema.py, sql/095_versions.sql) on a real database: the version sql/ makes is
the build's, an additive migration keeps the version before running, and a module refuses, saying what
to do, a schema it cannot run with."""

from __future__ import annotations

import asyncio
import logging
import re
from typing import Any

import psycopg
import pytest

from gwc import db, schema
from gwc.config import Config
from gwc.schema import SCHEMA_VERSION, SchemaMismatch, SchemaState

LOG = logging.getLogger("test.schema")


def test_the_schema_sql_makes_is_this_builds_version(db_conn: psycopg.Connection[Any]) -> None:
    reached = [
        int(m.group(1))
        for p in db.sql_files()
        for m in re.finditer(r"select schema_version_reached\((\d+),", p.read_text())
    ]
    assert max(reached) == SCHEMA_VERSION
    assert schema.read(db_conn) == SchemaState(SCHEMA_VERSION, 1)


def test_an_additive_migration_keeps_the_version_before_running_and_is_never_undone(
    db_conn: psycopg.Connection[Any], cell_config: Config
) -> None:
    n = SCHEMA_VERSION + 1
    db_conn.execute(
        "alter table lot_status add column if not exists upgrade_note text;"
        f"select schema_version_reached({n}, {SCHEMA_VERSION}, 'lot_status.upgrade_note')"
    )
    db_conn.commit()
    state = schema.read(db_conn)
    assert state == SchemaState(n, SCHEMA_VERSION) and state.runs(SCHEMA_VERSION) and state.runs(n)
    db.init_schema(cell_config, LOG)  # the older build's `gwc db init` after the newer one's
    assert schema.read(db_conn) == SchemaState(n, SCHEMA_VERSION)
    with db.connect(cell_config, "msched", LOG, 1) as conn:  # a module of the older build starts
        assert schema.check(conn) == SchemaState(n, SCHEMA_VERSION)
    asyncio.run(schema.check_at_start(cell_config, "ls", LOG))


def test_a_module_refuses_a_schema_it_cannot_run_with_and_says_what_to_do(
    db_conn: psycopg.Connection[Any], cell_config: Config
) -> None:
    assert SchemaState(SCHEMA_VERSION + 1, SCHEMA_VERSION + 1).problem() is not None
    db_conn.execute(
        f"select schema_version_reached({SCHEMA_VERSION + 2}, {SCHEMA_VERSION + 1}, 'drops what the old build reads')"
    )
    db_conn.commit()
    with pytest.raises(SchemaMismatch, match="runs builds of schema .* upgrade this host's package"):
        asyncio.run(schema.check_at_start(cell_config, "msched", LOG))
    older = SchemaState(SCHEMA_VERSION - 1, 1) if SCHEMA_VERSION > 1 else None
    if older is not None:
        assert "apply this build's schema first" in (older.problem() or "")
    db_conn.execute("drop table schema_version")
    db_conn.commit()
    with db.connect(cell_config, "msched", LOG, 1) as conn, pytest.raises(SchemaMismatch, match="gwc db init"):
        schema.check(conn)
