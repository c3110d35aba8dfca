"""What every part of an operation entity stands on: its database reads (LotReads) and what it has
heard of the cell, with the waits its steps are made of (Heard); see gwc/lot/entity.py."""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import psycopg

from gwc import db
from gwc.errors import DatabaseUnavailable
from gwc.ipc.bus import Bus, Peer
from gwc.ipc.catalogue import Message
from gwc.ipc.names import Msg
from gwc.lot.errors import LotTimeout
from gwc.lot.model import HISTORY, POLL, SHUT, T
from gwc.lot.state import EntityState
from gwc.retry import Deadline

# PostgreSQL's refusal when a role's connection limit is reached (gwc_lot's: gwc/budget.py).
OVER_BUDGET = "too many connections for role"
BUDGET_PAUSE_S = 0.5  # s between tries while the lot scripts' connections are all taken
BUDGET_SAY_S = 30.0  # s: how often the lot's log says it still waits for one


class LotReads:
    """The entity's reads of the tables (as role gwc_lot): it writes none."""

    def __init__(self, facts: EntityState) -> None:
        self.facts = facts
        self.conn: psycopg.Connection[Any] | None = None

    def _db(self) -> psycopg.Connection[Any]:
        if self.conn is None or self.conn.closed:
            self.conn = db.connect(self.facts.cfg, role="lot", log=self.facts.log, attempts=1)  # query asks again
            # The entity only reads, one statement at a time: each its own transaction, one round trip
            # (not BEGIN, the statement, COMMIT).
            self.conn.autocommit = True
        return self.conn

    def query(self, sql: str, *params: Any, within: float | None = None) -> list[tuple[Any, ...]]:
        """Read rows. A database away is read again after a pause, as a server away is asked again, for
        `within` seconds (Timeouts.retry by default; 0 for a read that is only a fallback)."""
        log = self.facts.log
        backoff = self.facts.timeouts.asking(within)
        said = 0.0
        while True:
            try:
                rows = db.transaction(self._db, db.Statement(sql, params, "all"), log=log)
            except DatabaseUnavailable as e:
                self.release()
                if OVER_BUDGET in str(e):  # lot scripts' share of the connections is taken: wait, never fail
                    if time.monotonic() - said >= BUDGET_SAY_S:
                        said = time.monotonic()
                        log.warning("lot scripts hold every connection they may (gwc/budget.py): waiting")
                    time.sleep(BUDGET_PAUSE_S)
                    continue
                pause = backoff.next()
                if pause is None:
                    raise
                log.warning("%s; reading again in %.1fs", e, pause)
                time.sleep(pause)
            else:
                self.release()
                return rows

    def release(self) -> None:
        """Close the entity's connection: a lot holds one only while it reads (reads are rare on its path,
        a connect costs a few ms), so that a cell of many lots waiting for machines holds none for them
        (docs/lot-scripts.md, Admission)."""
        conn, self.conn = self.conn, None
        if conn is not None:
            with contextlib.suppress(psycopg.Error):
                conn.close()

    def query_one(self, sql: str, *params: Any) -> tuple[Any, ...] | None:
        rows = self.query(sql, *params)
        return rows[0] if rows else None


class Heard:
    """What the entity has heard of the cell, under one lock (`cond`, notified at every news): its runs'
    completions, the status history of the machines it works with, modules' deaths, who is on the bus,
    and its own moves. The steps wait on it (`wait`)."""

    def __init__(self, facts: EntityState) -> None:
        self.facts = facts
        self.cond = threading.Condition()
        self.runs: dict[tuple[str, int], str] = {}  # (machine, run) -> ack code, from RUN_COMPL
        self.results: dict[tuple[str, int], dict[str, str]] = {}  # our runs' results that came with it
        # Every machine's status changes as (when, status, machine_run_id), from UPD_ME_ST (and MACHINE_STATUS
        # when a wait reads it): a Shutdown stays known after the machine is up again.
        self.history: dict[str, list[tuple[float, str, int | None]]] = {}
        self.deaths: dict[str, list[tuple[float, str]]] = {}  # module -> (when, how), from MOD_DIED
        self.peer_inc: dict[str, int] = {}  # bus peers present now -> incarnation
        self.peer_left: dict[str, float] = {}  # bus peers that left -> when
        self.began: dict[tuple[str, int], tuple[float, int | None]] = {}  # (machine, run) -> when, its WC's inc
        self.moved: list[tuple[str, int | None]] = []  # LOT_MOVED (action, lot_id) for this entity
        self.about: collections.Counter[str] = collections.Counter()  # machine -> its news heard

    # ----------------------------------------------------------------- news

    def hear(self, m: Message) -> None:
        """(bus thread) One broadcast (RUN_COMPL, UPD_ME_ST, MOD_DIED) or LOT_MOVED of this entity."""
        with self.cond:
            if m.name in (Msg.RUN_COMPLETE, Msg.UPDATE_ME_STATUS):
                self.about[str(m.machine_id)] += 1
            if m.name == Msg.RUN_COMPLETE and m.machine_run_id is not None:
                key = (m.machine_id, int(m.machine_run_id))
                self.runs[key] = m.ack_code
                if key in self.began and _all_str(m.results):
                    self.results[key] = m.results
            elif m.name == Msg.UPDATE_ME_STATUS:
                self.note(m.machine_id, m.status, m.machine_run_id)
            elif m.name == Msg.MODULE_DIED:
                deaths = self.deaths.setdefault(m.module, [])
                deaths.append((time.monotonic(), m.how))
                del deaths[:-HISTORY]
            elif m.name == Msg.LOT_MOVED and int(m.entity_id) == self.facts.entity_id:
                self.moved.append((m.action, m.lot_id))
            self.cond.notify_all()

    def watch_peers(self, bus: Bus) -> None:
        """(bus thread) Keep who is on the bus, and since when a module left, for the steps that wait on one."""
        with self.cond:
            self.peer_inc.update({name: p.inc for name, p in bus.peers().items()})
        bus.peer_listeners.append(self.peer_changed)

    def peer_changed(self, name: str, peer: Peer | None) -> None:
        with self.cond:
            if peer is None:
                self.peer_inc.pop(name, None)
                self.peer_left[name] = time.monotonic()
            else:
                if name not in self.peer_inc and name.startswith("wc:"):
                    self._first_heard(name[3:], peer.inc)
                self.peer_inc[name] = peer.inc
            self.cond.notify_all()

    def _first_heard(self, machine_id: str, inc: int) -> None:
        """(under the lock) A WC heard of for the first time (WCs leave a lot's query at sign-on to their
        beat: gwc/wc/wc.py): runs begun on its machine before are its, so that from now on a restart of
        that WC (a new incarnation) tells the run is lost to it, as for a WC known when the run began."""
        for key, (when, known) in list(self.began.items()):
            if key[0] == machine_id and known is None:
                self.began[key] = (when, inc)

    def present(self, name: str) -> bool:
        """Is `name` on the bus now (as this entity's bus last heard)?"""
        with self.cond:
            return name in self.peer_inc

    def begin(self, machine_id: str, machine_run_id: int, anew: bool = True) -> float:
        """The run's life on the machine begins now (anew; else unless it began already): what happens to
        the machine from then on counts for the run. Returns now."""
        now = time.monotonic()
        with self.cond:
            key, since = (machine_id, machine_run_id), (now, self.peer_inc.get(f"wc:{machine_id}"))
            if anew:
                self.began[key] = since
            else:
                self.began.setdefault(key, since)
        return now

    # ----------------------------------------------------------------- the machines' status history

    def note(self, machine_id: str, status: str, machine_run_id: int | None) -> None:
        """(under the lock) Remember a status change of a machine."""
        changes = self.history.setdefault(machine_id, [])
        changes.append((time.monotonic(), status, None if machine_run_id is None else int(machine_run_id)))
        del changes[:-HISTORY]

    def went(
        self, machine_id: str, since: float, statuses: Sequence[str], machine_run_id: int | None = None
    ) -> tuple[float, str, int | None] | None:
        """(under the lock) The first change of the machine, since `since`, into one of `statuses` or, if
        machine_run_id is given, to another run: (when, status, its machine_run_id)."""
        for when, status, run in self.history.get(machine_id, ()):
            if when >= since and (
                status in statuses or (machine_run_id is not None and run is not None and run != machine_run_id)
            ):
                return when, status, run
        return None

    def died(self, module: str, since: float) -> tuple[float, str] | None:
        """(under the lock) The first death of `module` an agent announced since `since`: (when, how)."""
        for when, how in self.deaths.get(module, ()):
            if when >= since:
                return when, how
        return None

    def lost(self, machine_id: str, machine_run_id: int) -> str | None:
        """(under the lock) Why the machine's WC will not answer for this run any more, if it will not."""
        since, inc = self.began.get((machine_id, machine_run_id), (time.monotonic(), None))
        died = self.died(f"me:{machine_id}", since)
        if died is not None:
            return f"me:{machine_id} died ({died[1]})"
        if self.went(machine_id, since, SHUT) is not None:
            return f"{machine_id} shut down"
        wc = f"wc:{machine_id}"
        now_inc = self.peer_inc.get(wc)
        if now_inc is None:
            away = time.monotonic() - max(since, self.peer_left.get(wc, since))
            if away > self.facts.timeouts.lost_grace:
                return f"{wc} is not on the bus ({away:.1f}s)"
        elif inc is not None and now_inc != inc:
            return f"{wc} restarted"
        return None

    # ----------------------------------------------------------------- waiting

    def wait(
        self,
        predicate: Callable[[], T | bool | None],
        timeout: float,
        what: str,
        poll: Callable[[], None] | None = None,
    ) -> T:
        """Wait until predicate() (called under the lock) is truthy; LotTimeout naming `what` after timeout.

        `poll`, if given, runs every POLL seconds outside the lock: a fallback read of the tables. Not
        at once: what the broadcasts said is known already, and a read now would hold the GIL while the
        bus thread sends the step this wait is for.
        """
        deadline = Deadline(timeout)
        next_poll = time.monotonic() + POLL
        while True:
            if poll is not None and time.monotonic() >= next_poll:
                poll()
                next_poll = time.monotonic() + POLL
            with self.cond:
                value = predicate()
                if value:
                    return value  # type: ignore[return-value]
                left = deadline.left()
                if left <= 0:
                    self.facts.log.error("timed out after %.0fs waiting for %s", timeout, what)
                    raise LotTimeout(
                        f"entity {self.facts.entity_id}: timed out after {timeout:.0f}s waiting for {what}"
                    )
                self.cond.wait(max(0.0, min(left, 0.5, next_poll - time.monotonic() if poll else 0.5)))


def _all_str(results: Any) -> bool:
    """Whether a Run_Complete's results are what a WC sends (param -> value, all text); else they are read
    from MACHINE_RUN_RESULT."""
    return isinstance(results, dict) and all(isinstance(p, str) and isinstance(v, str) for p, v in results.items())
