"""The agent's side of lot scripts that outlive their host (issue 36; gwc/lothosts.py, sql/092_lot_hosts.sql).

In a cell over several hosts each agent beats once a second: it renews its host, names the lot scripts it
runs or queues and the hosts whose agents it hears on the bus (alive, though their beats may be stale
after a database outage), and is answered with the scripts of dead hosts it must start now (queued as `gwc order
new`'s are: their processes resume their entities from LOT_TRAVELLERS) and with those of its own another
host took over meanwhile (this host was cut off, not dead), which it kills without a restart. The beat
is asynchronous, on the agent's loop (the agent runs no thread: it forks lot scripts), each bounded:
a database that is away, or a member whose host is dead, never holds the agent's loop.

Started ahead. Where lot scripts run as the lot user each is a fresh interpreter, exec'd: about 0.3 s
of CPU before its first line, a second or more when several start in a failover's rush, while the
machines their lots hold wait. So each beat also reads which scripts the other hosts run (a few per
host), and when a host's agent falls silent on the bus (its host dead, or cut off) this agent starts
that host's scripts ahead, each gated (`python -m gwc.lot.run --gate FD`: imported, touching
nothing, waiting on a pipe), as many as its budget has places for. Claimed, a started-ahead script is
adopted (the agent's `adopt_lot`) and told to go; the others are let go (the pipe closed: they exit,
having done nothing) when their host is heard again, another host claimed them, or after
AHEAD_KEEP_S. The claim itself stays the database's, as before.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import time
from dataclasses import dataclass
from typing import Any, Protocol

import psycopg

from gwc import db
from gwc import lothosts as hosting
from gwc.agent.child import Child
from gwc.agent.states import LIVE, ProcessState
from gwc.budget import Budget
from gwc.config import Config
from gwc.errors import DatabaseError
from gwc.hostuser import LotUser
from gwc.ipc.bus import Bus
from gwc.lot.admission import LotQueue
from gwc.lot.run import Forked, exec_lot_script
from gwc.promotion import PROMOTION_WAIT_S

SAY_EVERY_S = 10.0  # s: how often a database that stays away is logged again
BEAT_TIMEOUT_S = 5.0  # s: a beat's bound (connect and query), beside the connection's own TCP watch
AGAIN_S = 0.25  # s: the next try after a beat that failed (the database failing over: take over soon after)
AHEAD_PER_HOST = 4  # the most scripts of one silent host started ahead
AHEAD_KEEP_S = 30.0  # s: a script started ahead and not claimed meanwhile is let go


class LotHost(Protocol):
    """What the beat needs of the agent."""

    cfg: Config
    log: logging.Logger
    children: dict[str, Child]
    queue: LotQueue
    budget: Budget
    bus: Bus

    lot_user: LotUser | None

    def spawn_lots(self, entities: list[int]) -> dict[str, int | None]: ...

    def lot_places(self) -> int: ...

    def adopt_lot(self, entity: int, process: Forked) -> bool: ...


@dataclass
class Ahead:
    """A lot script started ahead of its claim: whose host it ran on, its process and the pipe's write end."""

    host: str
    process: Forked
    gate: int
    since: float


class LotHosting:
    """One agent's beat (see the module docstring)."""

    def __init__(self, agent: LotHost) -> None:
        self.agent = agent
        self.host = str(agent.cfg.host)
        self.ttl = hosting.ttl(agent.cfg)
        self.conn: psycopg.AsyncConnection[Any] | None = None
        self.away: str | None = None
        # A freshly started agent claims nothing until it has heard the bus for two peer timeouts: a host
        # whose agent it hears is alive, whatever its beat says (stale after a database outage).
        self.listen_s = 2 * agent.cfg.bus.peer_timeout
        self.others: dict[str, list[int]] = {}  # host -> some scripts it runs, read at the last beat
        self.ahead: dict[int, Ahead] = {}  # entity -> its script started ahead
        self.going: list[Forked] = []  # scripts let go, to reap

    def pids(self) -> set[int]:
        """The scripts started ahead, and those let go not yet reaped: this beat waits for them."""
        return {a.process.pid for a in self.ahead.values()} | {p.pid for p in self.going}

    def mine(self) -> list[int]:
        """Entities whose scripts this agent runs, restarts or queues."""
        live = (*LIVE, ProcessState.BACKOFF)
        running = [
            int(c.proc.machine or 0) for c in self.agent.children.values() if c.proc.kind == "lot" and c.state in live
        ]
        return sorted({*running, *self.agent.queue.pending()})

    def heard(self) -> list[str]:
        """The hosts whose agents are on the bus now (alive: their scripts are theirs)."""
        return sorted(n.partition(":")[2] for n in self.agent.bus.peers() if n.startswith("agent:"))

    async def _beat(self, mine: list[int], room: int, heard: list[str]) -> hosting.Beat:
        try:
            async with asyncio.timeout(BEAT_TIMEOUT_S):
                if self.conn is None or self.conn.closed:
                    self.conn = await db.connect_async(self.agent.cfg, "agent", PROMOTION_WAIT_S)
                answer = await hosting.beat_async(self.conn, self.host, self.ttl, mine, room, heard)
                if self.agent.lot_user is not None:
                    self.others = await hosting.others_async(self.conn, self.host, AHEAD_PER_HOST)
                return answer
        except (psycopg.Error, TimeoutError) as e:
            if self.conn is not None:
                await self.conn.close()
            self.conn = None
            raise DatabaseError(f"lot hosts' beat: {e or f'no answer within {BEAT_TIMEOUT_S:g}s'}") from e

    async def run(self) -> None:
        log = self.agent.log
        log.info(
            "lot scripts outlive this host: beating every %gs, a host silent %gs is taken over",
            hosting.BEAT_S,
            self.ttl,
        )
        said = 0.0
        loop = asyncio.get_running_loop()
        started = loop.time()
        try:
            while True:
                room = max(0, self.agent.budget.running * 4) if loop.time() - started >= self.listen_s else 0
                try:
                    answer = await self._beat(self.mine(), room, self.heard())
                except DatabaseError as e:
                    if self.away is None or loop.time() - said >= SAY_EVERY_S:
                        said = loop.time()
                        log.warning("lot hosts: cannot beat (%s): scripts of dead hosts wait", e)
                    self.away = str(e)
                    self._ahead(loop.time() - started >= self.listen_s)
                    await asyncio.sleep(AGAIN_S)
                    continue
                else:
                    if self.away is not None:
                        log.info("lot hosts: beating again")
                        self.away = None
                    self._obey(answer)
                    self._let_go(fresh=True)
                self._ahead(loop.time() - started >= self.listen_s)
                await asyncio.sleep(hosting.BEAT_S)
        finally:
            for entity in list(self.ahead):
                self._release(entity)
            for process in self.going:
                if process.popen is not None:
                    with contextlib.suppress(OSError):
                        process.popen.kill()
                        process.popen.wait()
            if self.conn is not None:
                await self.conn.close()

    def _ahead(self, listened: bool) -> None:
        """Start ahead the scripts of hosts whose agents are silent on the bus (see the module docstring),
        as many as the budget has places for; let go those no longer wanted."""
        user = self.agent.lot_user
        if user is None:
            return
        self._let_go(fresh=False)
        if not listened:
            return
        heard = set(self.heard())
        mine = set(self.mine())
        places = self.agent.lot_places() - len(self.ahead)
        for host, entities in self.others.items():
            if host in heard or host == self.host:
                continue
            for entity in entities:
                if places <= 0:
                    return
                if entity in self.ahead or entity in mine:
                    continue
                read, write = os.pipe()
                try:
                    process = exec_lot_script(self.agent.cfg, entity, user, gate=read)
                except OSError as e:
                    os.close(write)
                    self.agent.log.error("lot hosts: could not start the script of entity %d ahead: %s", entity, e)
                    return
                finally:
                    os.close(read)
                self.ahead[entity] = Ahead(host, process, write, time.monotonic())
                places -= 1
                self.agent.log.info(
                    "lot hosts: %s is silent on the bus: the script of entity %d started ahead (pid %d), "
                    "waiting for its claim",
                    host,
                    entity,
                    process.pid,
                )

    def _let_go(self, fresh: bool) -> None:
        """Let go the scripts started ahead that will not be claimed here: their host is heard again, or
        (`fresh`: the list of other hosts' scripts was just read) their host runs them no more (another
        claimed them, or they ended), or they waited AHEAD_KEEP_S. Reap those let go before."""
        heard = set(self.heard())
        now = time.monotonic()
        for entity, ahead in list(self.ahead.items()):
            gone = fresh and entity not in self.others.get(ahead.host, [])
            if ahead.host in heard or gone or now - ahead.since > AHEAD_KEEP_S:
                self._release(entity)
        self.going = [p for p in self.going if p.popen is not None and p.popen.poll() is None]

    def _release(self, entity: int) -> None:
        """Let one script started ahead go: its pipe closed, it exits having touched nothing."""
        ahead = self.ahead.pop(entity)
        with contextlib.suppress(OSError):
            os.close(ahead.gate)
        self.going.append(ahead.process)

    def _obey(self, answer: hosting.Beat) -> None:
        log = self.agent.log
        for entity in answer.lost:
            name = f"lot:{entity}"
            self.agent.queue.remove(entity)
            child = self.agent.children.get(name)
            if child is not None and child.state in (*LIVE, ProcessState.BACKOFF):
                log.error("%s: another host took its entity over (this host was cut off): killing it, no restart", name)
                if child.retry is not None:
                    child.retry.cancel()
                    child.retry = None
                if child.state == ProcessState.BACKOFF:  # no process: only the restart to forget
                    child.change_state(ProcessState.STOPPED, "taken over by another host")
                    self.agent.children.pop(name, None)
                    continue
                child.change_state(ProcessState.STOPPING, "taken over by another host")
                child.signal_group(signal.SIGKILL)
        if answer.take:
            log.warning(
                "lot hosts: taking over the scripts of %d entities of a dead host: %s",
                len(answer.take),
                ", ".join(map(str, answer.take)),
            )
            rest = []
            for entity in answer.take:
                ahead = self.ahead.pop(entity, None)
                if ahead is None:
                    rest.append(entity)
                elif self.agent.adopt_lot(entity, ahead.process):
                    try:
                        os.write(ahead.gate, b"g")
                    except OSError as e:  # it died meanwhile: its watch restarts it
                        log.warning("lot:%d: the script started ahead did not take the go (%s)", entity, e)
                    finally:
                        os.close(ahead.gate)
                else:
                    self.ahead[entity] = ahead
                    self._release(entity)
                    rest.append(entity)
            if rest:
                self.agent.spawn_lots(rest)


__all__ = ["LotHosting"]
