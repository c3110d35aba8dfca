"""A database failing over, seen from a connect (gwc/db/connect.py's `promotion_wait`).

Under Patroni the live members refuse a read-write session while they are standbys, until one is
promoted. A connect that may wait (a module reconnecting, a standby trying its lease, the agent's beat)
holds a session on each such member meanwhile and asks it every PROMOTION_POLL_S whether it is still
in recovery: the promoted one is connected to at once, instead of at the caller's next try (a reconnect
backoff, a lease poll), and one query on an open session is far cheaper than the connect (a backend and
a SCRAM exchange) each of those tries made.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import psycopg

PROMOTION_POLL_S = 0.05
PROMOTION_WAIT_S = 3.0  # s: how long such a connect watches before it gives its caller the refusal


def read_only_refusal(e: BaseException) -> bool:
    """Whether libpq refused a member for `target_session_attrs=read-write` because it is a standby (or
    its sessions are read-only): a database failing over, not one that is away."""
    text = str(e)
    return "hot standby" in text or "session is read-only" in text


def await_promotion(params: dict[str, Any], until: float, over: Callable[[], bool]) -> psycopg.Connection[Any] | None:
    """Hold a session on a member that refused for being a standby and ask it every PROMOTION_POLL_S
    whether it is still in recovery; once it is not, the read-write connection to it (None when `until`
    passes, `over()` says the caller has its answer, or the member goes away)."""
    try:
        watch = psycopg.connect(**{**params, "target_session_attrs": "any"}, autocommit=True)
    except psycopg.Error:
        return None
    try:
        while time.monotonic() < until and not over():
            row = watch.execute("select pg_is_in_recovery()").fetchone()
            if row is not None and not row[0]:
                try:
                    return psycopg.connect(**params, autocommit=False)
                except psycopg.Error as e:
                    if not read_only_refusal(e):
                        return None
            time.sleep(PROMOTION_POLL_S)
    except psycopg.Error:
        return None
    finally:
        watch.close()
    return None


async def await_promotion_async(params: dict[str, Any], until: float) -> psycopg.AsyncConnection[Any] | None:
    """await_promotion on an event loop (the connection autocommit, as connect_async's)."""
    loop = asyncio.get_running_loop()
    try:
        watch = await psycopg.AsyncConnection.connect(**{**params, "target_session_attrs": "any"}, autocommit=True)
    except psycopg.Error:
        return None
    try:
        while loop.time() < until:
            row = await (await watch.execute("select pg_is_in_recovery()")).fetchone()
            if row is not None and not row[0]:
                try:
                    return await psycopg.AsyncConnection.connect(**params, autocommit=True)
                except psycopg.Error as e:
                    if not read_only_refusal(e):
                        return None
            await asyncio.sleep(PROMOTION_POLL_S)
    except psycopg.Error:
        return None
    finally:
        await watch.close()
    return None
