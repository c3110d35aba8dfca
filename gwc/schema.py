"""Schema versions (issue 36): what schema this build's sql/ makes, and whether a database's will do.

The database records its schema's version and the oldest version whose builds still run on it
(sql/095_versions.sql, SCHEMA_VERSION's one row). Migrations stay compatible with the version before
(they only add), so during a rolling upgrade the new build's `gwc db init` runs first and the old
build's modules go on running on the newer schema. A module checks at start (gwc/module.py) and
refuses, saying what to do, a database whose schema it cannot run with: older than its own (the
migration has not been applied), or newer and no longer compatible with it (its host must be upgraded).
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc import db
from gwc.config import Config
from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.ipc import wire

# The schema version sql/ makes. A sql/ file that changes the schema ends with
# `select schema_version_reached(N, C, '...')` and this becomes N (a unit test checks they agree).
SCHEMA_VERSION = 2


class SchemaMismatch(DatabaseError):
    """This build cannot run with the database's schema. Not transient: nothing is retried."""


@dataclass(frozen=True)
class SchemaState:
    """The database's schema: its version, and the oldest version whose builds run on it."""

    version: int
    compatible_from: int

    def runs(self, ours: int = SCHEMA_VERSION) -> bool:
        """Whether a build of schema version `ours` runs with this database."""
        return self.compatible_from <= ours <= self.version

    def problem(self, ours: int = SCHEMA_VERSION) -> str | None:
        """What is wrong for a build of schema version `ours`, and what to do; None if it runs."""
        if ours > self.version:
            return (
                f"the database's schema is version {self.version}, this build needs {ours}: "
                "apply this build's schema first (`gwc db init` with it, on any host)"
            )
        if ours < self.compatible_from:
            return (
                f"the database's schema is version {self.version}, which runs builds of schema "
                f"{self.compatible_from} and later only; this build is of schema {ours}: upgrade this host's package"
            )
        return None


def read(conn: psycopg.Connection[Any]) -> SchemaState | None:
    """The database's schema state; None when it records none (a schema older than versions).
    Leaves no transaction open on the connection."""
    try:
        row = conn.execute("select version, compatible_from from schema_version").fetchone()
    except psycopg.errors.UndefinedTable:
        row = None
    except psycopg.OperationalError:
        raise
    except psycopg.Error as e:
        raise DatabaseError(f"cannot read the schema version: {e}") from e
    finally:
        if not conn.closed and not conn.autocommit:
            conn.rollback()
    return SchemaState(int(row[0]), int(row[1])) if row else None


def check(conn: psycopg.Connection[Any]) -> SchemaState | None:
    """Raise SchemaMismatch unless this build runs with the database's schema (a database that
    records no version predates versions: this build's schema has not been applied to it)."""
    state = read(conn)
    if state is None:
        raise SchemaMismatch(
            f"the database records no schema version, this build needs {SCHEMA_VERSION}: "
            "apply this build's schema first (`gwc db init` with it, on any host)"
        )
    why = state.problem()
    if why is not None:
        raise SchemaMismatch(why)
    return state


async def check_at_start(cfg: Config, role: str | None, log: logging.Logger) -> None:
    """A module's check at start: SchemaMismatch (it exits, saying what to do) when this build cannot
    run with the database's schema. A database away now is not waited for: the module rides the
    outage out as it does any other, and the check is made again at its next start."""
    if role is None:
        return
    try:
        conn = await asyncio.to_thread(db.connect, cfg, role, log, 1)
    except DatabaseUnavailable as e:
        log.warning("schema version not checked (the database is away: %s)", e)
        return
    with conn:
        state = check(conn)
    assert state is not None
    log.info(
        "schema: the database's is version %d (runs builds of %d..%d), this build's %d; wire versions %d..%d",
        state.version,
        state.compatible_from,
        state.version,
        SCHEMA_VERSION,
        wire.MIN_VERSION,
        wire.VERSION,
    )
