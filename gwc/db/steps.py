"""One database step, one transaction: `transaction` runs a step, retries it on transient failures
and dies cleanly on fatal ones (thesis 3.2.2); a `Statement` is a step of one SQL statement, run alone
in autocommit."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

import psycopg

from gwc.db.connect import one_line
from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.retry import Backoff

T = TypeVar("T")

_log = logging.getLogger("gwc.db")

ConnectionSource = psycopg.Connection[Any] | Callable[[], psycopg.Connection[Any]]


class Statement:
    """A database step that is one SQL statement: fetch "one" (a row or None), "all" (the rows) or None.

    `transaction` runs it alone, in autocommit: PostgreSQL makes a single statement atomic by itself,
    so the step needs no BEGIN and no COMMIT, each a round trip of its own (a one-row read takes about
    a third of the time, a one-row update two thirds, and the client's CPU halves: docs/performance.md).
    Made from one SQL text, it cannot grow a second statement that would then run outside a transaction.
    The connection is left in the mode it was in.
    """

    __slots__ = ("fetch", "into", "params", "sql")

    def __init__(
        self, sql: str, params: Any = (), fetch: str | None = "one", into: Callable[[Any], Any] | None = None
    ) -> None:
        if fetch not in ("one", "all", None):
            raise ValueError(f"fetch must be 'one', 'all' or None, not {fetch!r}")
        self.sql, self.params, self.fetch = sql, params, fetch
        self.into = into  # what a store makes of the fetched row(s): a dataclass (or a refusal raised)

    def __call__(self, cur: psycopg.Cursor[Any]) -> Any:
        cur.execute(self.sql, self.params)
        if self.fetch == "one":
            got = cur.fetchone()
        else:
            got = cur.fetchall() if self.fetch == "all" else None
        return got if self.into is None else self.into(got)


def _autocommit(conn: psycopg.Connection[Any], on: bool) -> bool:
    """Switch autocommit where psycopg allows it (an open connection outside a transaction); True if done."""
    if conn.closed or conn.info.transaction_status != psycopg.pq.TransactionStatus.IDLE:
        return False
    conn.autocommit = on
    return True


def transaction(
    conn: ConnectionSource,
    fn: Callable[[psycopg.Cursor[Any]], T],
    *,
    attempts: int = 3,
    log: logging.Logger | None = None,
) -> T:
    """Run fn(cursor) as one transaction and commit; retry the whole step on transient failures.

    `conn` is a connection or, better, a function returning one (like Module.db): a broken
    connection is closed and the function is called again for a fresh one. Anything left
    uncommitted on the connection beforehand is rolled back first. Transient failures
    (OperationalError: serialization failure, deadlock, lost connection, admin shutdown) are
    retried; after the last try, or at once for any other database error (constraint
    violation, bad SQL), DatabaseError is raised with the psycopg error as __cause__
    (DatabaseUnavailable when the connection was lost, or could not be made again). An
    exception of fn's own that is not a database error rolls back and propagates unchanged.

    A `Statement` runs alone, without BEGIN and COMMIT (see there).

    fn may run more than once: it must not have side effects outside the database. A commit
    lost with its connection may in fact have happened, so a step should be idempotent
    (ON CONFLICT, "where not exists") when it can be retried after a lost connection.
    """
    log = log or _log
    attempts = max(1, attempts)
    backoff = Backoff(0.05, 1.0, attempts=attempts, jitter=0.5)
    while True:
        attempt = backoff.tries + 1
        c = conn() if callable(conn) else conn
        try:
            if c.info.transaction_status != psycopg.pq.TransactionStatus.IDLE:
                c.rollback()
            was = c.autocommit  # a connection kept in autocommit (a lot script's) is left so
            alone = isinstance(fn, Statement) and (was or _autocommit(c, True))
            try:
                with c.cursor() as cur:
                    result = fn(cur)
            finally:
                if alone and not was:
                    _autocommit(c, False)
            if not alone:
                c.commit()
            return result
        except psycopg.OperationalError as e:
            _safe_rollback(c)
            broken = c.broken or c.closed
            if broken:
                c.close()
            pause = None if broken and not callable(conn) else backoff.next()
            log.warning(
                "database transaction failed (try %d of %d)%s: %s",
                attempt,
                attempts,
                ", connection lost" if broken else "",
                one_line(e),
            )
            if pause is None:
                # A step that lost its connection is not refused: the database is away (ask again later).
                error = DatabaseUnavailable if broken else DatabaseError
                raise error(
                    f"database step failed after {attempt} tries: {one_line(e)}"
                    + (" (connection lost)" if broken else "")
                ) from e
            time.sleep(pause)
        except psycopg.Error as e:
            _safe_rollback(c)
            raise DatabaseError(f"database step refused: {one_line(e)}") from e
        except BaseException:
            _safe_rollback(c)
            raise


def _safe_rollback(conn: psycopg.Connection[Any]) -> None:
    with contextlib.suppress(psycopg.Error):
        if not conn.closed:
            conn.rollback()
