"""MSCHED's step worker: the changes the conversations ask for, gathered and run as steps.

A step is ONE transaction: the changes gathered since the last step, then one scheduling pass
(gwc.msched.store.Step). Under load many changes share a step (group commit), which is where the
scheduler's throughput comes from; a change that fails in a batch is run again alone, so one bad
change fails alone.

The transaction runs in a thread of its own, one step at a time. The event loop meanwhile keeps
reading the bus, acknowledging datagrams and gathering the next step's changes: while a step waited
for the database on the loop itself, nothing was acknowledged, and under load a step longer than the
bus's `ack_timeout` (20 ms) made its peers retransmit to MSCHED (at 10,000 queued on a loaded
machine, about seven datagrams in ten were retransmissions: docs/performance.md, *The scheduler*).

The module's one database connection (gwc.moduledb.ModuleDatabase) is shared by the step thread
and the event loop (the sweep's look at the queue, the start): `Msched.transaction` lets one of them
use it at a time; the database watch (`ModuleDatabase.probe`) sees a step in flight as the database
used now. The step thread never makes a connection: that is the loop's, where an outage is noticed
and reconnected.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import psycopg

from gwc import db
from gwc.errors import DatabaseUnavailable
from gwc.log import TRACE
from gwc.moduledb import ModuleDatabase
from gwc.msched import store
from gwc.msched.policy import Policy
from gwc.msched.store import Outcome, Step

# Group commit: the worker takes its batch once GATHER_TURNS event-loop turns brought no new change
# (a datagram already received needs about three turns - read, open the conversation, run its
# handler - to become one), or after MAX_GATHER_TURNS turns under a steady stream.
GATHER_TURNS = 4
MAX_GATHER_TURNS = 200
LAZY_S = 0.5  # an acknowledged outcome waits at most this long for a step to ride on

Op = Callable[[Step], Any]
T = TypeVar("T")


class StepWorker:
    """Gathers the changes of conversations and runs them as steps; hands each step's outcomes on."""

    def __init__(
        self, database: ModuleDatabase, policy: Policy, log: logging.Logger, tell: Callable[[list[Outcome]], None]
    ) -> None:
        self.database = database  # the module's connection and its outages
        self.policy = policy
        self.log = log
        self.tell = tell  # called on the event loop with the outcomes of each committed step
        self.lock = threading.Lock()  # one user of the module's connection at a time
        self.step_conn: psycopg.Connection | None = None  # the connection the running step uses
        self._ops: list[tuple[Op, asyncio.Future[Any] | None]] = []
        # Unreserve_Me and acknowledged outcomes of one step go to the database as one statement each.
        self._frees: list[tuple[int, str | None, asyncio.Future[list[str]]]] = []
        self._finished: list[int] = []
        self._lazy: asyncio.TimerHandle | None = None  # a step for _finished, should no other come
        self._kick = asyncio.Event()  # set: changes are pending (or acknowledged outcomes wait)

    # ------------------------------------------------------------------ what the handlers call

    def submit(self, op: Op, wait: bool = True) -> asyncio.Future[Any]:
        """Queue a change for the next step; the future gives the op's result once it is committed."""
        fut = asyncio.get_running_loop().create_future() if wait else None
        self._ops.append((op, fut))
        self._wake()
        return fut  # type: ignore[return-value]

    def free(self, entity_id: int, machine_id: str | None) -> asyncio.Future[list[str]]:
        """Unreserve_Me for the next step, where it joins the step's other frees in one statement."""
        fut: asyncio.Future[list[str]] = asyncio.get_running_loop().create_future()
        self._frees.append((entity_id, machine_id, fut))
        self._wake()
        return fut

    def forget(self, request_key: int) -> None:
        """Its entity acknowledged the outcome (or never will): forget it in the next step, or in one of
        its own LAZY_S later should no other come. Kept that moment longer it is only told again (and
        dropped as late) should MSCHED restart meanwhile."""
        self._finished.append(request_key)
        if self._lazy is None:
            self._lazy = asyncio.get_running_loop().call_later(LAZY_S, self._kick.set)

    @property
    def busy(self) -> bool:
        """A step is running or waiting to run."""
        return self.lock.locked() or bool(self._ops or self._frees)

    def step_connection(self) -> psycopg.Connection:
        """The running step's connection; lost, the step fails DatabaseUnavailable (the loop reconnects)."""
        conn = self.step_conn
        if conn is None or conn.closed:
            raise DatabaseUnavailable("the scheduler's database connection was lost during a step")
        return conn

    # ------------------------------------------------------------------ the worker

    async def run(self) -> None:
        """The worker task: a step whenever changes are pending, one at a time."""
        kick = self._kick
        while True:
            await kick.wait()
            # Group commit: conversations already received join this step. Keep letting the loop turn
            # while changes keep coming (a backlog), up to a bound; a lone change waits a few turns.
            quiet = turns = 0
            while quiet < GATHER_TURNS and turns < MAX_GATHER_TURNS:
                n = len(self._ops) + len(self._frees)
                await asyncio.sleep(0)
                turns += 1
                quiet = quiet + 1 if len(self._ops) + len(self._frees) == n else 0
            kick.clear()
            batch = self._take()
            if batch.size:
                await self._run(batch)

    def _wake(self) -> None:
        self._kick.set()

    def _take(self) -> _Batch:
        """The pending changes as one step: the frees, the acknowledged outcomes, the other ops."""
        ops, self._ops = self._ops, []
        frees, self._frees = self._frees, []
        finished, self._finished = self._finished, []
        if self._lazy is not None:
            self._lazy.cancel()
            self._lazy = None
        return _Batch(frees, finished, ops)

    async def _step(self, work: Callable[[psycopg.Cursor[Any]], store.StepDone]) -> store.StepDone:
        """One transaction for a step, in the step thread. The connection is made here, on the loop; a
        connection lost during the step is made again here once and the step run again (as
        gwc.db.transaction does on the loop), else DatabaseUnavailable."""
        for attempt in (1, 2):
            self.step_conn = self.database.connection()
            try:
                return await asyncio.to_thread(self._in_thread, work)
            except DatabaseUnavailable:
                if attempt == 2 or (self.step_conn is not None and not self.step_conn.closed):
                    raise
            finally:
                self.step_conn = None
        raise AssertionError("unreachable")

    def _in_thread(self, work: Callable[[psycopg.Cursor[Any]], store.StepDone]) -> store.StepDone:
        with self.lock:
            # In flight, the step is the database used now: the watch (ModuleDatabase.probe) leaves
            # the connection alone until it is done.
            self.database.used = math.inf
            try:
                return db.transaction(self.step_connection, work, log=self.log)
            finally:
                self.database.used = time.monotonic()

    async def _run(self, batch: _Batch) -> None:
        """One step for the batch, then tell. A batch of several changes that fails is run again change by change."""
        started = time.perf_counter()
        frees, ops = batch.frees, batch.ops
        try:
            done = await self._step(
                store.step(self.policy, [(e, m) for e, m, _ in frees], batch.finished, [op for op, _ in ops])
            )
        except DatabaseUnavailable as e:
            # Nothing was done: whoever waits is answered DB_Badrea (asks again); what nobody waits
            # for (forgetting told outcomes, the sweep) rides on the first step once it is back.
            self._finished += batch.finished
            for _, _, waiter in frees:
                if not waiter.done():
                    waiter.set_exception(e)
            for op, fut in ops:
                if fut is None:
                    self._ops.append((op, None))
                elif not fut.done():
                    fut.set_exception(e)
            return
        except Exception as e:
            if batch.size > 1:
                self.log.warning("a step of %d changes failed (%s): running them one by one", batch.size, e)
                for one in batch.split():
                    await self._run(one)
                return
            alone: asyncio.Future[Any] | None = frees[0][2] if frees else ops[0][1] if ops else None
            if alone is None:
                self.log.error("step failed: %s", e)
            elif not alone.done():
                alone.set_exception(e)
            return
        # The outcomes first: an entity bound is told before the changes' askers are answered (a lot
        # that freed a machine hears its Unreserve_Me_Ack after the next lot heard it has it).
        self.tell(done.outcomes)
        for (_, _, waiter), freed in zip(frees, done.freed):
            if not waiter.done():
                waiter.set_result(freed)
        for (_, fut), result in zip(ops, done.results):
            if fut is not None and not fut.done():
                fut.set_result(result)
        self.log.log(
            TRACE,
            "step of %d change(s): %d outcome(s) in %.2f ms",
            batch.size,
            len(done.outcomes),
            (time.perf_counter() - started) * 1000,
        )


@dataclass
class _Batch:
    """The changes of one step: Unreserve_Me (each with its waiter), acknowledged outcomes, other ops."""

    frees: list[tuple[int, str | None, asyncio.Future[list[str]]]]
    finished: list[int]
    ops: list[tuple[Op, asyncio.Future[Any] | None]]

    @property
    def size(self) -> int:
        return len(self.frees) + (1 if self.finished else 0) + len(self.ops)

    def split(self) -> list[_Batch]:
        """Each change as a step of its own (the acknowledged outcomes together)."""
        alone = [_Batch([f], [], []) for f in self.frees]
        if self.finished:
            alone.append(_Batch([], self.finished, []))
        return alone + [_Batch([], [], [op]) for op in self.ops]
