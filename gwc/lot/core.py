"""The operation entity's own state: its database reads and traveller, the status history of the
machines it works with, and the waits its steps are made of (see gwc/lot/entity.py)."""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from typing import Any

import psycopg

from gwc import db
from gwc.config import Config
from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import Message
from gwc.ipc.codes import AckCode
from gwc.lot.errors import LotTimeout, MachineLost
from gwc.lot.model import (
    HISTORY,
    POLL,
    SHUT,
    UP,
    MachineRequest,
    Reservation,
    Run,
    T,
    Timeouts,
    now_text,
    save_traveller,
)

# PostgreSQL's refusal when a role's connection limit is reached (gwc_lot's: gwc/budget.py).
OVER_BUDGET = "too many connections for role"
BUDGET_PAUSE_S = 0.5  # s between tries while the lot scripts' connections are all taken
BUDGET_SAY_S = 30.0  # s: how often the lot's log says it still waits for one


class EntityCore:
    """What every step of an operation entity stands on: state, reads, record, waits."""

    def __init__(
        self, cfg: Config, entity_id: int, log: logging.Logger, timeouts: Timeouts | None = None, max_tries: int = 3
    ) -> None:
        self.cfg = cfg
        self.entity_id = int(entity_id)
        self.name = f"lot:{self.entity_id}"
        self.log = log
        self.timeouts = timeouts or Timeouts()
        self.max_tries = max_tries
        # What the lot script decides for a run in doubt past its bound (runs.py): "hold" (the safe
        # default for a physical part: the entity stops, failed with the reason) or "reroute".
        self.in_doubt = "hold"
        self.lot_id: int | None = None
        self.state: str | None = None
        self.product_id: str | None = None
        self.priority: int | None = None
        self.work_order_id: int | None = None
        self.script_id: str | None = None  # LOT_SCRIPTS' row for the lot (read with it at open)
        self.script_path: str | None = None
        self.result: str | None = None
        self._bus: BlockingBus | None = None
        self._conn: psycopg.Connection[Any] | None = None
        self._cond = threading.Condition()
        self._runs: dict[tuple[str, int], str] = {}  # (machine, run) -> ack code, from RUN_COMPL
        self._heard_results: dict[tuple[str, int], dict[str, str]] = {}  # our runs' results that came with it
        # Every machine's status changes as (when, status, machine_run_id), from UPD_ME_ST (and MACHINE_STATUS
        # when a wait reads it): a Shutdown stays known after the machine is up again.
        self._history: dict[str, list[tuple[float, str, int | None]]] = {}
        self._deaths: dict[str, list[tuple[float, str]]] = {}  # module -> (when, how), from MOD_DIED
        self._peer_inc: dict[str, int] = {}  # bus peers present now -> incarnation
        self._peer_left: dict[str, float] = {}  # bus peers that left -> when
        self._began: dict[tuple[str, int], tuple[float, int | None]] = {}  # (machine, run) -> when, its WC's inc
        # The machines whose news (UPD_ME_ST, RUN_COMPL) the entity hears: bound to it and not given back.
        self._watching: set[str] = set()
        self._in_cell = False  # its lot is imported: it hears MOD_DIED
        self._heard_about: collections.Counter[str] = collections.Counter()  # machine -> its news heard
        self._requests: list[MachineRequest] = []  # asked for and not yet waited for
        self._asked: list[MachineRequest] = []  # every request this process made
        self._groups = 0
        self._moved: list[tuple[str, int | None]] = []
        # Progress reports (waiting_machine, running) on their way to the Lot Server, in order (report()).
        self._reporter: concurrent.futures.ThreadPoolExecutor | None = None
        self._reports: list[concurrent.futures.Future[Message]] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._failed = False
        self.traveller: dict[str, Any] = {"entity_id": self.entity_id, "steps": []}

    # ----------------------------------------------------------------- the database, the record

    def _db(self) -> psycopg.Connection[Any]:
        if self._conn is None or self._conn.closed:
            self._conn = db.connect(self.cfg, role="lot", log=self.log, attempts=1)  # _query asks again
            # The entity only reads, one statement at a time: each its own transaction, one round trip
            # (not BEGIN, the statement, COMMIT).
            self._conn.autocommit = True
        return self._conn

    def _query(self, sql: str, *params: Any, within: float | None = None) -> list[tuple[Any, ...]]:
        """Read rows. A database away is read again after a pause, as a server away is asked again, for
        `within` seconds (Timeouts.retry by default; 0 for a read that is only a fallback)."""
        backoff = self.timeouts.asking(within)
        said = 0.0
        while True:
            try:
                rows = db.transaction(self._db, db.Statement(sql, params, "all"), log=self.log)
            except DatabaseUnavailable as e:
                self._release()
                if OVER_BUDGET in str(e):  # lot scripts' share of the connections is taken: wait, never fail
                    if time.monotonic() - said >= BUDGET_SAY_S:
                        said = time.monotonic()
                        self.log.warning("lot scripts hold every connection they may (gwc/budget.py): waiting")
                    time.sleep(BUDGET_PAUSE_S)
                    continue
                pause = backoff.next()
                if pause is None:
                    raise
                self.log.warning("%s; reading again in %.1fs", e, pause)
                time.sleep(pause)
            else:
                self._release()
                return rows

    def _release(self) -> None:
        """Close the entity's connection: a lot holds one only while it reads (reads are rare on its path,
        a connect costs a few ms), so that a cell of many lots waiting for machines holds none for them
        (docs/lot-scripts.md, Admission)."""
        conn, self._conn = self._conn, None
        if conn is not None:
            with contextlib.suppress(psycopg.Error):
                conn.close()

    def read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        """Rows of a read of the tables (role gwc_lot: reads only), asked again while the database is away:
        for library code beside the entity (gwc.quality.store)."""
        return self._query(sql, *params)

    def _query_one(self, sql: str, *params: Any) -> tuple[Any, ...] | None:
        rows = self._query(sql, *params)
        return rows[0] if rows else None

    def _set_state(self, state: str) -> None:
        self.state = state
        self.traveller["state"] = str(state)

    def _record(self, op_type: str, res: Reservation, runs: list[Run], note: str) -> None:
        self.traveller["steps"].append(
            {
                "op_type": op_type,
                "machine_run_id": res.machine_run_id,
                "request_key": res.request_key,
                "machines": res.machines,
                "runs": [asdict(r) for r in runs],
                "note": note,
                "at": now_text(),
            }
        )
        self._save()

    def _save(self) -> None:
        """Write the traveller (var/lots/entity-E.json) whole; it is a record, never required."""
        try:
            save_traveller(self.cfg, self.entity_id, self.traveller)
        except OSError as e:
            self.log.warning("could not write the traveller: %s", e)

    # ----------------------------------------------------------------- the machines' status history

    def _note(self, machine_id: str, status: str, machine_run_id: int | None) -> None:
        """(under the lock) Remember a status change of a machine."""
        changes = self._history.setdefault(machine_id, [])
        changes.append((time.monotonic(), status, None if machine_run_id is None else int(machine_run_id)))
        del changes[:-HISTORY]

    def _went(
        self, machine_id: str, since: float, statuses: Sequence[str], machine_run_id: int | None = None
    ) -> tuple[float, str, int | None] | None:
        """(under the lock) The first change of the machine, since `since`, into one of `statuses` or, if
        machine_run_id is given, to another run: (when, status, its machine_run_id)."""
        for when, status, run in self._history.get(machine_id, ()):
            if when >= since and (
                status in statuses or (machine_run_id is not None and run is not None and run != machine_run_id)
            ):
                return when, status, run
        return None

    def _died(self, module: str, since: float) -> tuple[float, str] | None:
        """(under the lock) The first death of `module` an agent announced since `since`: (when, how)."""
        for when, how in self._deaths.get(module, ()):
            if when >= since:
                return when, how
        return None

    def _lost(self, machine_id: str, machine_run_id: int) -> str | None:
        """(under the lock) Why the machine's WC will not answer for this run any more, if it will not."""
        since, inc = self._began.get((machine_id, machine_run_id), (time.monotonic(), None))
        died = self._died(f"me:{machine_id}", since)
        if died is not None:
            return f"me:{machine_id} died ({died[1]})"
        if self._went(machine_id, since, SHUT) is not None:
            return f"{machine_id} shut down"
        wc = f"wc:{machine_id}"
        now_inc = self._peer_inc.get(wc)
        if now_inc is None:
            away = time.monotonic() - max(since, self._peer_left.get(wc, since))
            if away > self.timeouts.lost_grace:
                return f"{wc} is not on the bus ({away:.1f}s)"
        elif inc is not None and now_inc != inc:
            return f"{wc} restarted"
        return None

    def _read_status(self, machines: Sequence[str], statuses: Sequence[str], machine_run_id: int | None) -> None:
        """Fallback for a missed UPD_ME_ST: a machine found in one of `statuses` (or, if machine_run_id is
        given, on another run) in MACHINE_STATUS is noted as having changed now."""
        try:
            rows = self._query(
                "SELECT machine_id, status, machine_run_id FROM machine_status WHERE machine_id = ANY(%s)",
                list(machines),
                within=0,
            )
        except DatabaseError as e:
            self.log.warning("could not read MACHINE_STATUS: %s", e)
            return
        with self._cond:
            for m, status, run in rows:
                other = machine_run_id is not None and run is not None and run != machine_run_id
                known = self._history.get(m)
                if (status in statuses or other) and not (known and known[-1][1:] == (status, run)):
                    self.log.info("%s is %s (run %s) in MACHINE_STATUS", m, status, run)
                    self._note(m, status, run)
                    self._cond.notify_all()

    def _raise_if_lost(self, machine_id: str, machine_run_id: int, ack: Message | None) -> None:
        """A refusal (or no answer) because the machine is going or gone loses the machine: it shut down
        since the run began there, its WC left or restarted, it is not up now, or it cannot serve now."""
        with self._cond:
            why = self._lost(machine_id, machine_run_id)
        if why:
            raise MachineLost(why)
        row = self._query_one("SELECT status FROM machine_status WHERE machine_id = %s", machine_id)
        if row is None or row[0] not in UP:
            raise MachineLost(f"{machine_id} is {row[0] if row else 'unknown'}")
        if ack is not None and ack.ack_code == AckCode.NOTNOW:
            raise MachineLost(f"{machine_id} cannot serve now ({ack.note or ack.ack_code})")

    # ----------------------------------------------------------------- waiting

    def _wait(
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
        deadline = time.monotonic() + timeout
        next_poll = time.monotonic() + POLL
        while True:
            if poll is not None and time.monotonic() >= next_poll:
                poll()
                next_poll = time.monotonic() + POLL
            with self._cond:
                value = predicate()
                if value:
                    return value  # type: ignore[return-value]
                left = deadline - time.monotonic()
                if left <= 0:
                    self.log.error("timed out after %.0fs waiting for %s", timeout, what)
                    raise LotTimeout(f"entity {self.entity_id}: timed out after {timeout:.0f}s waiting for {what}")
                self._cond.wait(max(0.0, min(left, 0.5, next_poll - time.monotonic() if poll else 0.5)))

    def _pause(self, tries: int, what: str) -> None:
        """The pause before an operation's next try: a machine that just failed gets time to be marked
        down (or come up) rather than be asked again at once."""
        pause = self.timeouts.pause * 2 ** (tries - 1)
        self.log.info("%s in %.1fs", what, pause)
        time.sleep(pause)
