"""The agent's side of lot scripts that outlive their host (issue 36; gwc/lothosts.py, sql/092_lot_hosts.sql).

In a cell over several hosts each agent beats once a second: it renews its host, names the lot scripts it
runs or queues and the hosts whose agents it hears on the bus (alive, though their beats may be stale
after a database outage), and is answered with the scripts of dead hosts it must start now (queued as `gwc order
new`'s are: their processes resume their entities from LOT_TRAVELLERS) and with those of its own another
host took over meanwhile (this host was cut off, not dead), which it kills without a restart. The beat
is asynchronous, on the agent's loop (the agent runs no thread: it forks lot scripts), each bounded:
a database that is away, or a member whose host is dead, never holds the agent's loop.
"""

from __future__ import annotations

import asyncio
import logging
import signal
from typing import Any, Protocol

import psycopg

from gwc import db
from gwc import lothosts as hosting
from gwc.agent.child import Child
from gwc.agent.states import LIVE, ProcessState
from gwc.budget import Budget
from gwc.config import Config
from gwc.errors import DatabaseError
from gwc.ipc.bus import Bus
from gwc.lot.admission import LotQueue

SAY_EVERY_S = 10.0  # s: how often a database that stays away is logged again
BEAT_TIMEOUT_S = 5.0  # s: a beat's bound (connect and query), beside the connection's own TCP watch
AGAIN_S = 0.25  # s: the next try after a beat that failed (the database failing over: take over soon after)


class LotHost(Protocol):
    """What the beat needs of the agent."""

    cfg: Config
    log: logging.Logger
    children: dict[str, Child]
    queue: LotQueue
    budget: Budget
    bus: Bus

    def spawn_lots(self, entities: list[int]) -> dict[str, int | None]: ...


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
                    self.conn = await db.connect_async(self.agent.cfg, "agent")
                return await hosting.beat_async(self.conn, self.host, self.ttl, mine, room, heard)
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
                    await asyncio.sleep(AGAIN_S)
                    continue
                else:
                    if self.away is not None:
                        log.info("lot hosts: beating again")
                        self.away = None
                    self._obey(answer)
                await asyncio.sleep(hosting.BEAT_S)
        finally:
            if self.conn is not None:
                await self.conn.close()

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
            self.agent.spawn_lots(answer.take)


__all__ = ["LotHosting"]
