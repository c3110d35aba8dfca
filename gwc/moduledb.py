"""A bus module's database, a part every Module holds (gwc/module.py): its one connection, made on first
use and remade after a failure (thesis 3.2.2); an outage noticed, said once, and ridden out by a
task of its own that reconnects with backoff, so that no step and no heartbeat ever waits for a
database that is gone; and a cheap look at the connection while no step uses it.

What a new connection must do first (the lease claimed, MSCHED's lock taken) and what follows an
outage are the module's business: it hands them in as `prepare` and `back`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import select
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import psycopg

from gwc import db
from gwc.config import Config
from gwc.errors import DatabaseError, DatabaseUnavailable, GwcError
from gwc.lease import Deposed
from gwc.promotion import PROMOTION_WAIT_S
from gwc.retry import Backoff, Deadline

T = TypeVar("T")
# A module that uses the database watches it while nothing else does, so that a lost database is noticed
# (and reconnected to) within seconds, not at the next conversation that needs it. After DATABASE_WATCH_S
# without a step it looks at its connection's socket at each heartbeat: a server that stops or dies
# closes it, and a link cut off fails the kernel's keepalive probes (db.TCP_WATCH); either way it turns
# readable and then a query tells. One poll() and no round trip: a resting module's database costs
# neither it nor the server a wake-up.
DATABASE_WATCH_S = 1.0
RECONNECT_MAX_S = 0.5  # s: the longest pause between reconnects while the database is away (was 1 s)


class ModuleDatabase:
    """One module's connection and its outages. `down` is the monotonic time the database was found
    away, while it is; `connection()` raises DatabaseUnavailable at once meanwhile."""

    def __init__(
        self,
        cfg: Config,
        role: str | None,
        log: logging.Logger,
        prepare: Callable[[psycopg.Connection], None],
        deposed: Callable[[str], None],
        back: Callable[[float], Awaitable[None]],
        tasks: set[asyncio.Task[Any]],
    ) -> None:
        self.cfg, self.role, self.log = cfg, role, log
        self.prepare = prepare  # with every new connection, before it is used (Deposed, DatabaseUnavailable)
        self.deposed = deposed  # the module lost its lease
        self.back = back  # after an outage, with its length
        self.tasks = tasks  # the module's background tasks: the reconnecting one joins them
        self.conn: psycopg.Connection | None = None
        self.down: float | None = None
        self.why = ""
        self.up = asyncio.Event()
        self.used = 0.0  # monotonic time of the last step, for the probe

    def connection(self) -> psycopg.Connection:
        """The connection, made now if there is none (DatabaseUnavailable while the database is away)."""
        if self.conn is not None and not self.conn.closed:
            return self.conn
        if self.down is not None:
            raise DatabaseUnavailable(
                f"the cell database is away (for {time.monotonic() - self.down:.0f}s): ask again later"
            )
        try:
            conn = db.connect(self.cfg, role=self.role, log=self.log, attempts=1)
            self.prepare(conn)
        except Deposed as e:
            self.deposed(str(e))
            raise
        except DatabaseUnavailable as e:
            self.lost(e)
            raise
        self.conn = conn
        self.up.set()
        return conn

    def transaction(self, fn: Callable[[psycopg.Cursor[Any]], T]) -> T:
        """Run one step's database work as one transaction, retried on transient failures."""
        self.used = time.monotonic()
        return db.transaction(self.connection, fn, log=self.log)

    def adopt(self, conn: psycopg.Connection) -> None:
        """Take a connection made elsewhere (the one that took the module's lease)."""
        self.conn = conn
        self.used = time.monotonic()

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    async def wait_up(self, deadline: Deadline) -> bool:
        """Wait until the database is back (True), or the deadline passes (False)."""
        if self.down is None:
            return True
        try:
            left = deadline.left()
            await asyncio.wait_for(self.up.wait(), None if left == math.inf else left)
        except TimeoutError:
            return False
        return True

    def lost(self, e: DatabaseUnavailable) -> None:
        """The database is away: say so once, and reconnect in the background until it is back."""
        self.why = str(e)
        if self.down is not None:
            return
        self.down = time.monotonic()
        self.up.clear()
        self.close()
        self.log.error("the cell database is away (%s): serving what does not need it, reconnecting", e)
        task = asyncio.get_running_loop().create_task(self._reconnect())
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _reconnect(self) -> None:
        assert self.down is not None
        # 0.2 doubling to 0.5 s, unbounded: until the database is back or the module stops. The cap is what
        # a failover costs a module after the new primary is up (a WC: its runs stored, its machine freed).
        backoff = Backoff(0.2, RECONNECT_MAX_S)
        said = time.monotonic()
        while await backoff.asleep():
            try:
                # In a thread: connecting to a server that is away (a TCP address that does not answer)
                # may take up to connect_timeout, which the module's event loop must not wait for.
                # A database failing over: its standbys are watched for the one promoted (db.PROMOTION_POLL_S).
                conn = await asyncio.to_thread(db.connect, self.cfg, self.role, self.log, 1, PROMOTION_WAIT_S)
            except DatabaseError as e:
                self.why = str(e)
            else:
                try:
                    self.prepare(conn)
                except Deposed as e:
                    conn.close()
                    self.deposed(str(e))
                    return
                except DatabaseUnavailable as e:
                    conn.close()
                    self.why = str(e)
                else:
                    break
            if time.monotonic() - said >= 10:
                said = time.monotonic()
                self.log.warning("the cell database is still away after %.0fs: %s", said - self.down, self.why)
        down_for = time.monotonic() - self.down
        self.conn, self.down = conn, None
        self.up.set()
        self.log.warning("the cell database is back after %.1fs", down_for)
        try:
            await self.back(down_for)
        except GwcError as e:
            self.log.error("work after the database came back failed: %s", e)

    def probe(self) -> None:
        """Look at the database when no step did for a while, so that an outage is noticed."""
        if self.role is None or self.down is not None:
            return
        if time.monotonic() - self.used < DATABASE_WATCH_S:
            return
        conn = self.conn
        if conn is None or conn.closed or _readable(conn.fileno()):
            self.transaction(db.Statement("select 1", fetch=None))


def _readable(fd: int) -> bool:
    """Whether a socket has something to read (or was closed by its other end) now."""
    return bool(select.select([fd], [], [], 0)[0])
