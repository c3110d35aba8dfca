"""A connect that may wait watches a database failing over for its promoted member (gwc/db/connect.py,
`promotion_wait`), on a real database: while every member refuses a read-write session (a standby's
refusal, made here by the database's sessions being read-only), the connect holds a session on each and
connects as soon as one takes writes again, instead of failing back to its caller's next try."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import psycopg
import pytest
from psycopg import sql
from psycopg.conninfo import conninfo_to_dict, make_conninfo

from gwc import db, promotion
from gwc.config import Config
from gwc.db.connect import connect_any
from gwc.errors import DatabaseUnavailable
from gwc.retry import Deadline


def read_only(url: str, on: bool) -> None:
    """New sessions of the test's database read-only (a standby's refusal to read-write) or not."""
    name = conninfo_to_dict(url)["dbname"]
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("set default_transaction_read_only = off")  # (this session may be one of them)
        value = sql.SQL("on" if on else "default")
        conn.execute(
            sql.SQL("alter database {} set default_transaction_read_only = {}").format(sql.Identifier(name), value)
        )


def two_members(url: str) -> str:
    """The test's database named twice, as a cluster's members are, read-write wanted."""
    params = conninfo_to_dict(url)
    host = str(params["host"])
    return make_conninfo(**{**params, "host": f"{host},{host}", "target_session_attrs": "read-write"})


@contextmanager
def read_only_database(url: str) -> Iterator[None]:
    """The test's database refusing read-write sessions while the block runs (and never after it)."""
    read_only(url, True)
    try:
        yield
    finally:
        read_only(url, False)


def watched(url: str, application: str, members: int = 2) -> None:
    """Wait until a connect that was refused watches each member for its promotion: its watch sessions
    (application_name `application`) have asked pg_is_in_recovery()."""
    deadline = Deadline(10)
    with psycopg.connect(url, autocommit=True) as conn:
        while True:
            row = conn.execute(
                "select count(*) from pg_stat_activity where datname = current_database() "
                "and application_name = %s and query = 'select pg_is_in_recovery()'",
                (application,),
            ).fetchone()
            if row is not None and row[0] >= members:
                return
            if deadline.expired:
                raise AssertionError(f"the connect of {application} never watched its {members} members")
            time.sleep(0.01)


def test_a_refusal_for_read_only_is_told_apart_from_a_database_away(database_url: str) -> None:
    with read_only_database(database_url):
        with pytest.raises(psycopg.OperationalError) as refused:
            psycopg.connect(two_members(database_url)).close()
        assert promotion.read_only_refusal(refused.value)
        assert not promotion.read_only_refusal(psycopg.OperationalError("connection refused"))


def test_a_waiting_connect_is_made_as_soon_as_a_member_takes_writes(database_url: str) -> None:
    url = two_members(database_url)
    with read_only_database(database_url):
        started = time.monotonic()
        with pytest.raises(psycopg.OperationalError):  # no wait: refused at once, as before
            connect_any(url, "gwc_test")
        assert time.monotonic() - started < 1.0
        made: list[Any] = []
        waiting = threading.Thread(target=lambda: made.append(connect_any(url, "gwc_test", promotion_wait=10.0)))
        waiting.start()
        watched(database_url, "gwc_test")
        promoted = time.monotonic()
        read_only(database_url, False)  # the "promotion"
        waiting.join(10)
        took = time.monotonic() - promoted
        assert made, "the waiting connect gave up"
        conn = made[0]
        try:
            assert conn.execute("show transaction_read_only").fetchone() == ("off",)
        finally:
            conn.close()
        assert took < 1.0, took  # a poll (PROMOTION_POLL_S) and a connect, not a caller's next try


def test_a_waiting_connect_gives_up_after_its_wait(database_url: str) -> None:
    url = two_members(database_url)
    with read_only_database(database_url):
        started = time.monotonic()
        with pytest.raises(psycopg.OperationalError, match="read-only"):
            connect_any(url, "gwc_test", promotion_wait=0.6)
        assert 0.5 < time.monotonic() - started < 3.0


def test_the_agents_connect_waits_for_the_promotion_too(cell_config: Config, database_url: str) -> None:
    cfg = dataclasses.replace(cell_config, database_url=two_members(database_url))

    async def walk() -> float:
        waiting = asyncio.ensure_future(db.connect_async(cfg, "agent", promotion_wait=10.0))
        await asyncio.to_thread(watched, database_url, "gwc_agent")
        assert not waiting.done()
        promoted = time.monotonic()
        await asyncio.to_thread(read_only, database_url, False)
        conn = await asyncio.wait_for(waiting, 10)
        took = time.monotonic() - promoted
        try:
            cur = await conn.execute("show transaction_read_only")
            assert await cur.fetchone() == ("off",)
        finally:
            await conn.close()
        return took

    with read_only_database(database_url):
        with pytest.raises(DatabaseUnavailable):  # no wait: refused at once
            asyncio.run(db.connect_async(cfg, "agent"))
        assert asyncio.run(walk()) < 1.0
