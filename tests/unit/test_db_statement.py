"""db.Statement: a one-statement step runs alone (autocommit), without the BEGIN and COMMIT round trips of
db.transaction's other steps, and leaves the connection as it found it, failed or not."""

from __future__ import annotations

from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.errors import DatabaseError

# The transaction's start is its first statement's start only when no BEGIN came before it.
ALONE = "select transaction_timestamp() = statement_timestamp()"


def test_a_statement_is_sent_without_begin_and_a_step_of_several_with_it(db_conn: psycopg.Connection[Any]) -> None:
    assert db.transaction(db_conn, db.Statement(ALONE)) == (True,)
    assert db.transaction(db_conn, lambda cur: cur.execute(ALONE).fetchone()) == (False,)
    assert db_conn.autocommit is False
    assert db_conn.info.transaction_status == psycopg.pq.TransactionStatus.IDLE


def test_a_statements_write_is_committed_and_its_rows_fetched_as_asked(
    db_conn: psycopg.Connection[Any], database_url: str
) -> None:
    update = "update machine_status set note = %s where machine_id = %s returning machine_id"
    assert db.transaction(db_conn, db.Statement(update, ("alone", "wc1"))) == ("wc1",)
    assert db.transaction(db_conn, db.Statement(update, ("alone", "nowhere"))) is None
    assert db.transaction(db_conn, db.Statement("select 1 union all select 2", fetch="all")) == [(1,), (2,)]
    assert db.transaction(db_conn, db.Statement("select 1", fetch=None)) is None
    with psycopg.connect(database_url) as other:  # seen by another session: committed
        assert other.execute("select note from machine_status where machine_id = 'wc1'").fetchone() == ("alone",)
    with pytest.raises(ValueError, match="fetch"):
        db.Statement("select 1", fetch="many")


def test_a_refused_statement_raises_and_leaves_the_connection_usable_as_before(
    db_conn: psycopg.Connection[Any],
) -> None:
    with pytest.raises(DatabaseError, match="refused"):
        db.transaction(db_conn, db.Statement("update machine_status set status = 'Flying' where machine_id = 'wc1'"))
    assert db_conn.autocommit is False
    assert db.transaction(db_conn, lambda cur: cur.execute("select 1").fetchone()) == (1,)
    db_conn.execute("select 1")  # a step left open before: rolled back first, then the statement runs alone
    assert db.transaction(db_conn, db.Statement(ALONE)) == (True,)


def test_a_connection_kept_in_autocommit_stays_so(db_conn: psycopg.Connection[Any]) -> None:
    db_conn.autocommit = True  # as a lot script keeps its own
    assert db.transaction(db_conn, db.Statement(ALONE)) == (True,)
    assert db_conn.autocommit is True
