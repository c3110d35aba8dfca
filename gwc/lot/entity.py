"""The operation entity: Listing 1's calls as a Python API a process engineer writes lot scripts with.

A lot script is a Python file with a `main(entity)` function. For every entity of an order the
Human Interface starts `python -m gwc.lot.run --entity E`, which opens an OperationEntity (the
process joins the bus as `lot:E` and attaches to the Lot Server) and calls `main` with it:

    def main(entity: OperationEntity) -> None:
        entity.wait_for_import()                                  # the operator imports the lot
        op = entity.operate("alum_chess", [["cmm_wc"]])            # request, wait, set up, run, unreserve
        entity.lot_completed("PASS" if op.passed else "FAIL")
        entity.wait_for_export()                                  # the operator exports it

`operate` is the usual step; the calls it is made of (request_machines, wait_for_machines,
setup_run, start_run, wait_run_complete, run_results, unreserve) are there for scripts that need
to interleave them, as Listing 1 does.

Every step has a deadline (`Timeouts`) and fails with a LotError saying which step and why.
Leaving the `with` block on an exception (or on SIGTERM) cleans up what the entity holds: its
requests are cancelled, its machines unreserved and the entity marked failed with the reason, so a
failing script leaves nothing the cell cannot clean (thesis 3.2 warns a failing lot script could
corrupt the tables: this one asks the owners instead of writing them). A script killed with kill -9
cannot clean up; the Lot Server's reaper does the same for it when `lot:E` leaves the bus.

The entity listens to RUN_COMPL (its runs finish), UPD_ME_ST (a reserved machine shut down mid-run:
the step is retried, after a pause, on whatever machine is up, a bounded number of times) and
LOT_MOVED (the operator's import and export); to the first two only once its lot is in the cell
(imported), so that lots waiting to be imported are not woken by every run. It remembers every
status change of the machines it works with, so a machine that went Shutdown and came up again
while the entity waited is still known to have lost the run. Servers come and go too: a
conversation with the Lot Server or MSCHED that finds it away, restarting or not yet started is
asked again with a backoff for a bounded time (Timeouts.retry); every request the entity repeats
that way is safe to repeat.

It reads the tables (as role gwc_lot) and writes none. Besides its log it keeps a traveller,
var/lots/entity-E.json: what it ran where and what it decided, for the operator (`gwc lots show E`)
and the demonstration.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

import psycopg

from gwc import db
from gwc.config import Config
from gwc.errors import BusError, ConversationTimeout, DatabaseError, GwcError
from gwc.ipc.bus import Batch, BlockingBus, Bus, Conversation, Peer
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, LotState, MachineStatus
from gwc.lot.errors import LotError, LotTimeout, MachineLost, RequestCancelled, RequestRefused, RunFailed, ScriptStopped
from gwc.module import NOT_STARTED, ask

T = TypeVar("T")
S = LotState
LISTENS = ("RUN_COMPL", "UPD_ME_ST", "LOT_MOVED")
# Until its lot is imported an entity hears only its moves: the cell's machine traffic is no
# business of a lot waiting at the door, and in a busy cell many wait there.
WAITING_LISTENS = ("LOT_MOVED",)
UP = (MachineStatus.IDLE.value, MachineStatus.SETUP.value, MachineStatus.RUNNING.value)
FINISHED = (S.COMPLETED, S.WAITING_EXPORT, S.EXPORTED, S.FAILED)
IMPORTED = (S.IMPORTED, S.WAITING_MACHINE, S.RUNNING, *FINISHED)
FOREVER = 10.0**7  # a conversation MSCHED answers when it can: its own deadline is the caller's
BOUND_AT_ONCE = 0.01  # s: a request granted within this after its Machine_Req_Ack never waited
POLL = 1.0  # fallback reads of LOT_STATUS / MACHINE_STATUS while waiting for a broadcast
HISTORY = 32  # status changes remembered per machine
SHUT = (MachineStatus.SHUTDOWN.value,)
ENDED = (MachineStatus.SHUTDOWN.value, MachineStatus.IDLE.value)  # a machine in these runs nothing
# ENTITY_REQ actions whose repeat (its first answer was lost) may find the operator already moved the
# entity on: the Lot Server then answers Notnow with the state the first request led to.
ALREADY = {"import": (S.IMPORTED,), "export": (S.EXPORTED,)}


@dataclass(frozen=True)
class Timeouts:
    """Deadlines of the entity's steps, in seconds. Operator decisions get long ones."""

    answer: float = 10.0  # a server's answer to one conversation
    import_: float = 3600.0  # the operator imports the lot
    export: float = 3600.0  # the operator exports it
    machines: float = 600.0  # waiting in MSCHED's queue for machines
    setup: float = 300.0  # SETUP_RUN (the CMM waits for its start button to be pushed)
    run: float = 600.0  # from START_RUN to RUN_COMPL
    lost_grace: float = 3.0  # RUN_COMPL may still follow a machine's Shutdown (Run_Shut) or Idle
    cleanup: float = 5.0  # each cleanup conversation of a failing entity
    retry: float = 60.0  # asking a server (ls, msched) again while it is away, restarting or not started
    backoff: float = 0.2  # the first pause between those asks, doubling ...
    backoff_max: float = 2.0  # ... up to this
    pause: float = 1.0  # before an operation's next try after a machine was lost, doubling per try


class Backoff:
    """The pauses between asks of a server that cannot answer now: short, doubling, for a bounded time."""

    def __init__(self, timeouts: Timeouts, within: float | None = None) -> None:
        self.deadline = time.monotonic() + (timeouts.retry if within is None else within)
        self.delay = timeouts.backoff
        self.most = timeouts.backoff_max
        self.tries = 0

    def next(self) -> float | None:
        """The pause before the next ask, or None when the time for asking is up."""
        self.tries += 1
        left = self.deadline - time.monotonic()
        if left <= 0:
            return None
        pause, self.delay = min(self.delay, left), min(self.delay * 2, self.most)
        return pause


def _not_started(ack: Message) -> bool:
    """The module is on the bus but not started (yet, or any more): ask again later."""
    return ack.ack_code == AckCode.NOTNOW and ack.note == NOT_STARTED


@dataclass
class Reservation:
    """Machines MSCHED bound to the entity for one operation (Machine_Req_Comp ACK_OK)."""

    op_type: str
    machine_run_id: int
    request_key: int | None
    machines: list[str]


@dataclass
class Run:
    """One run of one machine and its MACHINE_RUN_RESULT rows."""

    machine_id: str
    recipe_id: str
    machine_run_id: int
    ack_code: str
    results: dict[str, str]

    @property
    def ok(self) -> bool:
        return self.ack_code == AckCode.ACK_OK


@dataclass
class Operation:
    """One operation done: where it ran and what the machines reported."""

    op_type: str
    machine_run_id: int
    runs: list[Run]
    tries: int = 1

    @property
    def ok(self) -> bool:
        """Every run completed (ACK_OK). Whether the part is good is `passed`."""
        return all(r.ok for r in self.runs)

    @property
    def machines(self) -> list[str]:
        return [r.machine_id for r in self.runs]

    @property
    def results(self) -> dict[str, str]:
        """All runs' results in one dict (param -> value); with several machines, keys are machine.param."""
        if len(self.runs) == 1:
            return dict(self.runs[0].results)
        return {f"{r.machine_id}.{k}": v for r in self.runs for k, v in r.results.items()}

    @property
    def passed(self) -> bool:
        """The runs completed and the results say the part is within tolerance (see `verdict`)."""
        return self.ok and verdict(self.results)[0]


FAIL_WORDS = {"FAIL", "FAILED", "REJECT", "REJECTED", "NOK", "OUT_OF_TOLERANCE"}
PASS_WORDS = {"PASS", "PASSED", "OK", "ACCEPT", "ACCEPTED", "IN_TOLERANCE"}


def verdict(results: dict[str, str]) -> tuple[bool, str]:
    """Is a measured part within tolerance, from its run results (thesis 3.2.3)?

    Understands the two forms our machines report: PASS/FAIL values (the CMM, per feature or
    overall) and numeric measurements with a tolerance (`deviation` / `tolerance`, or
    `<name>` with `<name>_nominal` and `<name>_tol`). Any failing value fails the part; no
    verdict at all fails it too (a measurement that says nothing does not pass a part).
    """
    fails, passes, why = [], 0, []
    for param, value in sorted(results.items()):
        word = str(value).strip().upper()
        if word in FAIL_WORDS:
            fails.append(param)
        elif word in PASS_WORDS:
            passes += 1
    lowered = {k.lower(): v for k, v in results.items()}
    checks: list[tuple[str, float, float, float]] = []
    if "deviation" in lowered and "tolerance" in lowered:
        with contextlib.suppress(ValueError):
            checks.append(("deviation", float(lowered["deviation"]), 0.0, float(lowered["tolerance"])))
    for k, v in lowered.items():
        if f"{k}_nominal" in lowered and f"{k}_tol" in lowered:
            with contextlib.suppress(ValueError):
                checks.append((k, float(v), float(lowered[f"{k}_nominal"]), float(lowered[f"{k}_tol"])))
    for name, value, nominal, tol in checks:
        if abs(value - nominal) > abs(tol):
            fails.append(name)
            why.append(f"{name} {value:g} off {nominal:g} by more than {abs(tol):g}")
        else:
            passes += 1
    if fails:
        return False, "out of tolerance: " + (", ".join(why) if why else ", ".join(fails))
    if passes:
        return True, "within tolerance"
    return False, "no verdict in the run results"


@dataclass
class _Alternative:
    """One MACH_REQ conversation: one alternative (a set of machines, all needed) of a request."""

    op_type: str
    machines: list[str]
    ack: Message | None = None
    comp: Message | None = None
    reserved: list[str] = field(default_factory=list)
    error: str | None = None
    done: bool = False
    group: MachineRequest | None = None

    @property
    def key(self) -> int | None:
        return self.ack.request_key if self.ack is not None else None

    @property
    def sibling_cancelled(self) -> bool:
        """MSCHED ended it because another alternative of the entity was satisfied, or refused it for
        that reason (Machine_Req_Ack REQ_CANCEL: a sibling of its alt_group was bound before it came)."""
        if self.ack is not None and self.ack.ack_code == AckCode.REQ_CANCEL:
            return True
        c = self.comp
        return c is not None and c.ack_code == AckCode.REQ_CANCEL and "satisfied" in (c.note or "")

    def describe(self) -> str:
        return " AND ".join(self.machines)


class _Call:
    """A conversation held on the bus thread for a step waiting in the script's thread (see _ask_wc)."""

    def __init__(self) -> None:
        self.answer: Message | None = None
        self.error: GwcError | None = None
        self.done = False
        self.task: asyncio.Task[None] | None = None
        self.abandoned = False


class MachineRequest:
    """The alternatives asked for one operation ((M1 AND M2) OR (M3)), as MSCHED answered them."""

    def __init__(self, op_type: str, alternatives: list[_Alternative], alt_group: str | None = None) -> None:
        self.op_type = op_type
        self.alternatives = alternatives
        self.alt_group = alt_group  # sent with each alternative: MSCHED binds at most one of them
        self.winner: _Alternative | None = None  # the alternative the entity took
        for a in alternatives:
            a.group = self

    def surplus(self, alt: _Alternative) -> list[str]:
        """Machines of a second bound alternative that the winner does not use: to be given back."""
        keep = set(self.winner.reserved or self.winner.machines) if self.winner else set()
        return [m for m in (alt.reserved or alt.machines) if m not in keep]

    @property
    def keys(self) -> list[int]:
        return [a.key for a in self.alternatives if a.key is not None]

    def describe(self) -> str:
        return " OR ".join(f"({a.describe()})" for a in self.alternatives)


class OperationEntity:
    """One operation entity: a lot script's handle on the cell (see the module docstring)."""

    def __init__(
        self, cfg: Config, entity_id: int, log: logging.Logger, timeouts: Timeouts | None = None, max_tries: int = 3
    ) -> None:
        self.cfg = cfg
        self.entity_id = int(entity_id)
        self.name = f"lot:{self.entity_id}"
        self.log = log
        self.timeouts = timeouts or Timeouts()
        self.max_tries = max_tries
        self.lot_id: int | None = None
        self.state: str | None = None
        self.product_id: str | None = None
        self.priority: int | None = None
        self.work_order_id: int | None = None
        self.result: str | None = None
        self._bus: BlockingBus | None = None
        self._conn: psycopg.Connection[Any] | None = None
        self._cond = threading.Condition()
        self._runs: dict[tuple[str, int], str] = {}
        # Every machine's status changes as (when, status, machine_run_id), from UPD_ME_ST (and MACHINE_STATUS
        # when a wait reads it): a Shutdown stays known after the machine is up again.
        self._history: dict[str, list[tuple[float, str, int | None]]] = {}
        self._peer_inc: dict[str, int] = {}  # bus peers present now -> incarnation
        self._peer_left: dict[str, float] = {}  # bus peers that left -> when
        self._began: dict[tuple[str, int], tuple[float, int | None]] = {}  # (machine, run) -> when, its WC's inc
        self._requests: list[MachineRequest] = []  # asked for and not yet waited for
        self._groups = 0
        self._recipes: dict[tuple[str, str], str] = {}  # (machine, op type) -> recipe, read ahead (_read_recipes)
        self._moved: list[tuple[str, int | None]] = []
        # Progress reports (waiting_machine, running) on their way to the Lot Server, in order (report()).
        self._reporter: concurrent.futures.ThreadPoolExecutor | None = None
        self._reports: list[concurrent.futures.Future[Message]] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._failed = False
        self.traveller: dict[str, Any] = {"entity_id": self.entity_id, "steps": []}

    # ----------------------------------------------------------------- life

    def __enter__(self) -> OperationEntity:
        try:
            self.open()
        except BaseException as e:
            self.__exit__(type(e), e, None)
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        try:
            if self.state in (S.COMPLETED, S.WAITING_EXPORT, S.EXPORTED):
                if exc is not None:  # its work is done: the lot stays as it is, the operator exports it
                    self.log.warning(
                        "lot script of entity %d stopped after its lot completed (%s): entity stays %s",
                        self.entity_id,
                        _reason(exc),
                        self.state,
                    )
            elif exc is not None:
                self.fail(_reason(exc))
            elif self.state != S.FAILED:
                self.fail("the lot script ended without completing its lot")
        finally:
            self.close()

    def open(self) -> None:
        """Join the bus as lot:E, listen, attach to the Lot Server (ENTITY_REQ attach, our pid)."""
        self._read_lot()
        if self.state in (S.FAILED, S.EXPORTED):
            self._failed = True  # nothing of ours to clean up
            raise LotError(f"entity {self.entity_id} is already {self.state}: nothing to do")
        self._bus = BlockingBus(
            self.name, self.cfg.bus, self.log, interest=LISTENS if self.state in IMPORTED else WAITING_LISTENS
        )
        self._bus.call_soon(self._watch_peers, self._bus.bus)
        self._bus.peers()  # returns after _watch_peers ran (the bus thread runs callbacks in order)
        self._spawn(self._listen())
        # Started now, not at the first report: starting a thread takes milliseconds on a busy machine.
        self._reporter = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"{self.name}-reports")
        self._reporter.submit(lambda: None)
        ack = self.entity_request("attach", script_pid=os.getpid())
        self.log.info(
            "entity %d attached (lot %s, product %s, state %s, pid %d)",
            self.entity_id,
            self.lot_id,
            self.product_id,
            ack.state,
            os.getpid(),
        )
        self.traveller.update(
            lot_id=self.lot_id, product_id=self.product_id, pid=os.getpid(), started=_now(), state=self.state
        )
        self._save()

    def close(self) -> None:
        """Leave the bus and the database. Safe to call twice."""
        if self._reporter is not None:  # a report still retrying fails fast once the bus is gone
            self._reporter.shutdown(wait=False, cancel_futures=True)
            self._reporter = None
        if self._bus is not None:
            bus, self._bus = self._bus, None
            bus.call_soon(self._cancel_tasks)
            with contextlib.suppress(Exception):
                bus.close()
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
            self._conn = None

    def fail(self, reason: str) -> None:
        """Give back everything and mark the entity failed: requests cancelled, machines unreserved."""
        if self._failed:
            return
        self._failed = True
        self.log.error("entity %d failed: %s; cleaning up", self.entity_id, reason)
        self.traveller.update(result=f"failed: {reason}")
        if self._bus is None:
            return
        if self._present("msched"):
            for what, fn in (("cancel its requests", self.cancel_requests), ("unreserve its machines", self.unreserve)):
                try:
                    fn(timeout=self.timeouts.cleanup)
                except GwcError as e:
                    self.log.error("cleanup: could not %s: %s", what, e)
        else:
            self.log.error("cleanup: msched is not on the bus; its reaper cleans up when it returns")
        with contextlib.suppress(GwcError):  # a refused report is why we fail, perhaps: the failure still goes
            self._drain_reports()
        try:  # asked again while the Lot Server is away (Timeouts.retry): else the entity stays as it is
            self.entity_request("failed", reason=reason[:500], timeout=self.timeouts.cleanup)
        except GwcError as e:
            self.log.error("cleanup: the Lot Server did not take the failure: %s", e)
        self._set_state(S.FAILED)
        self._save()

    # ----------------------------------------------------------------- the Lot Server

    def entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
    ) -> Message:
        """ENTITY_REQ: ask the Lot Server to move this entity (import, export, completed, failed ...).

        Asked again while the Lot Server is away or not started (see `_ask`). Every action is safe to
        repeat: the Lot Server moves an entity only into the state it is asked for (attach, completed,
        failed, waiting_machine, running: a repeat finds it there and changes nothing), and a repeated
        import or export that finds the operator already moved the entity on is taken as done (ALREADY).
        Progress reports sent before (report()) are answered first; one that failed raises here.
        """
        self._drain_reports()
        return self._entity_request(action, reason, script_pid, timeout, within)

    def report(self, action: str) -> None:
        """ENTITY_REQ for a progress state (waiting_machine, running), sent without waiting for the answer.

        The Lot Server records progress for the operator; the operation does not need its answer, so
        reports go in the background, one at a time and in order (asked again while the Lot Server is
        away, as entity_request is), and the next entity_request waits for them first. A report the
        Lot Server refuses raises there, at the latest when the lot completes or fails.
        """
        self._set_state(action)
        if self._reporter is None:
            raise LotError(f"entity {self.entity_id} is not open")
        self._reports.append(self._reporter.submit(self._entity_request, action, keep_state=True))

    def _drain_reports(self) -> None:
        reports, self._reports = self._reports, []
        for report in reports:
            report.result()

    def _entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
        keep_state: bool = False,
    ) -> Message:
        ack = self._ask(
            "ENTITY_REQ",
            message("Entity_Request", entity_id=self.entity_id, action=action, reason=reason, script_pid=script_pid),
            "ls",
            timeout,
            within,
        )
        if ack.ack_code == AckCode.NOTNOW and ack.state in ALREADY.get(action, ()):
            self.log.info("entity %d: %s already done (the entity is %s)", self.entity_id, action, ack.state)
        elif ack.ack_code != AckCode.ACK_OK:
            raise LotError(
                f"the Lot Server refused {action} for entity {self.entity_id}: {ack.ack_code}"
                + (f" ({ack.note})" if ack.note else "")
                + (f", entity is {ack.state}" if ack.state else "")
            )
        if ack.lot_id is not None:
            self.lot_id = ack.lot_id
        if ack.state and not keep_state:  # a report's answer comes after the script has moved on
            self._set_state(ack.state)
        return ack

    def read_state(self) -> str | None:
        """The entity's state in LOT_STATUS (None if the Lot Server has no row for it)."""
        row = self._query_one("SELECT state, lot_id FROM lot_status WHERE entity_id = %s", self.entity_id)
        if row is None:
            return None
        self.lot_id = row[1]
        return str(row[0])

    def wait_for_import(self, timeout: float | None = None) -> None:
        """Ask to be imported and wait for the operator's IMPORT_LOT (Listing 1's wait_for_import)."""
        state = self.read_state()
        if state in IMPORTED:
            self.log.info("entity %d already imported (%s)", self.entity_id, state)
        else:
            if state != S.WAITING_IMPORT:
                self.entity_request("import")
            self.log.info("entity %d waiting to be imported", self.entity_id)
            self._wait_moved("import", IMPORTED, timeout or self.timeouts.import_)
            self._set_state(S.IMPORTED)
            self.log.info("entity %d imported (lot %s)", self.entity_id, self.lot_id)
        self._listen_in_cell()

    def _listen_in_cell(self) -> None:
        """From now on hear the machines' news too (RUN_COMPL, UPD_ME_ST): the lot is in the cell."""
        if self._bus is not None and self._bus.bus.interests != frozenset(LISTENS):
            self._bus.set_interest(LISTENS)

    def lot_completed(self, result: str | None = None) -> None:
        """Tell the Lot Server the lot's work here is done, with its result (Listing 1's lot_completed).

        First every request of the entity still queued in MSCHED is cancelled: nothing may wait for
        machines on behalf of a finished entity.
        """
        self._cancel_leftovers("before completing")
        self.entity_request("completed", reason=result)
        self.result = result
        self.traveller.update(result=result or "completed")
        self.log.info("entity %d completed: %s", self.entity_id, result or "done")
        self._save()

    def wait_for_export(self, timeout: float | None = None) -> None:
        """Ask to be exported and wait for the operator's EXPORT_LOT (Listing 1's wait_for_export)."""
        state = self.read_state()
        if state != S.EXPORTED:
            if state != S.WAITING_EXPORT:
                self.entity_request("export", reason=self.result)  # the Lot Server keeps it as the reason
            self.log.info("entity %d waiting to be exported", self.entity_id)
            self._wait_moved("export", (S.EXPORTED,), timeout or self.timeouts.export)
        self._set_state(S.EXPORTED)
        self._save()
        self.log.info("entity %d exported (lot %s)", self.entity_id, self.lot_id)

    # ----------------------------------------------------------------- MSCHED

    def qualified_machines(self, op_type: str, up_only: bool = True) -> list[str]:
        """Machines with a recipe for op_type (OP_MACHINE_RECIPE), those that are up if `up_only`."""
        sql = (
            "SELECT DISTINCT r.machine_id FROM op_machine_recipe r JOIN machine_status s USING (machine_id) "
            "WHERE r.op_type = %s" + (" AND s.status = ANY(%s)" if up_only else "") + " ORDER BY 1"
        )
        rows = self._query(sql, op_type, *([list(UP)] if up_only else []))
        return [r[0] for r in rows]

    def request_machines(
        self, op_type: str, alternatives: Sequence[Sequence[str]], priority: int | None = None
    ) -> MachineRequest:
        """MACH_REQ: one request per alternative (all machines of an alternative are needed).

        Returns once MSCHED acknowledged each (queued with a request_key, or NO_MACHINE). All of them
        carry one new alt_group, so MSCHED binds at most one: a sibling that reaches it after another
        was bound is refused (Machine_Req_Ack REQ_CANCEL), which the entity takes as a sibling cancel.
        """
        alts = [_Alternative(op_type, list(a)) for a in alternatives if a]
        if not alts:
            raise RequestRefused(f"no machines to ask for {op_type}")
        self._listen_in_cell()  # already, unless the script skipped wait_for_import
        self._groups += 1  # unique per call (and per process: a restarted script's groups are new ones)
        request = MachineRequest(op_type, alts, f"{self.entity_id}.{os.getpid()}.{self._groups}")
        self._requests.append(request)
        for alt in alts:
            self._spawn(self._request(alt, priority if priority is not None else self.priority))
        self._read_recipes(op_type, {m for a in alts for m in a.machines})
        self._wait(
            lambda: all(a.ack is not None or a.done for a in alts),
            self.timeouts.retry + self.timeouts.answer + 1,
            f"MSCHED's answer to the request for {op_type}",
        )
        for a in alts:
            if a.ack is not None and a.ack.ack_code == AckCode.ACK_OK:
                self.log.info("request %s for %s (%s) queued", a.key, op_type, a.describe())
            elif a.sibling_cancelled:
                self.log.info("request for %s (%s) not queued: another alternative is bound", op_type, a.describe())
            else:
                self.log.warning(
                    "request for %s (%s) refused: %s",
                    op_type,
                    a.describe(),
                    a.error or (a.ack.ack_code if a.ack else "no answer"),
                )
        return request

    def wait_for_machines(self, request: MachineRequest, timeout: float | None = None) -> Reservation:
        """Wait for MSCHED to bind one alternative (Machine_Req_Comp ACK_OK): machines and machine_run_id."""
        timeout = timeout or self.timeouts.machines
        alts = request.alternatives

        surplus: list[str] = []

        def outcome() -> _Alternative | bool:
            bound = [a for a in alts if a.comp is not None and a.comp.ack_code == AckCode.ACK_OK]
            if bound:
                request.winner = bound[0]
                surplus.extend(m for a in bound[1:] for m in request.surplus(a))
                return bound[0]
            return all(a.done for a in alts) and not any(a.sibling_cancelled for a in alts)

        try:
            with self._cond:  # MSCHED's Machine_Req_Comp follows its Machine_Req_Ack when it binds at once
                got = self._cond.wait_for(outcome, BOUND_AT_ONCE)
            if not got and self.state != S.WAITING_MACHINE:  # not bound at once: it waits, say so
                self.report(S.WAITING_MACHINE)
            got = got or self._wait(outcome, timeout, f"machines for {request.op_type} ({request.describe()})")
        finally:
            if request in self._requests:
                self._requests.remove(request)
        for m in surplus:  # MSCHED bound two alternatives: keep the first, give the other back
            self.log.warning("%s was bound too by another alternative: giving it back", m)
            self.unreserve(m)
        if isinstance(got, _Alternative):
            if any(not a.done for a in alts if a is not got):  # a sibling may still be queued: end it
                self._cancel_leftovers("after taking an alternative", request)
            assert got.comp is not None
            res = Reservation(request.op_type, int(got.comp.machine_run_id or 0), got.key, got.reserved or got.machines)
            self.log.info(
                "got machine_run_id %d on %s for %s (request %s)",
                res.machine_run_id,
                ", ".join(res.machines),
                res.op_type,
                res.request_key,
            )
            self.report(S.RUNNING)
            return res
        cancelled = [a for a in alts if a.comp is not None and a.comp.ack_code == AckCode.REQ_CANCEL]
        if cancelled:
            notes = "; ".join(f"request {a.key}: {a.comp.note or 'cancelled'}" for a in cancelled if a.comp)
            self.log.error("machine request for %s cancelled (REQ_CANCEL): %s", request.op_type, notes)
            raise RequestCancelled(f"machine request for {request.op_type} was cancelled (REQ_CANCEL): {notes}")
        errors = [a.error for a in alts if a.error]
        if errors:
            raise LotError(f"machine request for {request.op_type} failed: {'; '.join(errors)}")
        codes = sorted({(a.comp or a.ack).ack_code for a in alts if a.comp or a.ack})
        raise RequestRefused(f"no machine for {request.op_type} ({request.describe()}): {', '.join(codes)}")

    def reserve(
        self,
        op_type: str,
        alternatives: Sequence[Sequence[str]] | None = None,
        priority: int | None = None,
        timeout: float | None = None,
    ) -> Reservation:
        """Request machines and wait for them; when none can serve now, wait for one to come up and ask again.

        Without alternatives, each machine qualified for op_type that is up is one alternative.
        """
        deadline = time.monotonic() + (timeout or self.timeouts.machines)
        for attempt in range(1, self.max_tries + 1):
            alts = [list(a) for a in alternatives] if alternatives else [[m] for m in self.qualified_machines(op_type)]
            try:
                if alts:
                    request = self.request_machines(op_type, alts, priority)
                    return self.wait_for_machines(request, max(0.1, deadline - time.monotonic()))
                reason = f"no machine qualified for {op_type} is up"
            except RequestRefused as e:
                reason = str(e)
            if attempt == self.max_tries:
                raise RequestRefused(f"{reason} (asked {attempt} times)")
            self.log.warning("%s: waiting for a machine to come up, then asking again", reason)
            self._pause(attempt, f"asking MSCHED for {op_type} again")
            self._wait_machine_up(op_type, alternatives, deadline)
        raise AssertionError("unreachable")

    def cancel_requests(
        self, request_key: int | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """CANCEL_RE: cancel one request, or all of the entity's. Returns how many were cancelled."""
        ack = self._ask(
            "CANCEL_RE",
            message(
                "Cancel_Request",
                request_key=request_key,
                entity_id=None if request_key else self.entity_id,
                by=self.name,
            ),
            "msched",
            timeout,
            within,
        )
        if ack.ack_code not in (AckCode.ACK_OK, AckCode.REQ_KEY_U):
            raise LotError(f"MSCHED refused to cancel the requests of entity {self.entity_id}: {ack.ack_code}")
        return int(ack.cancelled or 0)

    def unreserve(
        self, machine_id: str | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """UNRESERVE: free one reserved machine, or all of the entity's. Returns how many were freed."""
        ack = self._ask(
            "UNRESERVE",
            message("Unreserve_Me", entity_id=self.entity_id, machine_id=machine_id, by=self.name),
            "msched",
            timeout,
            within,
        )
        if ack.ack_code == AckCode.NOT_RESERVED:
            self.log.info("unreserve %s: nothing reserved", machine_id or "all")
            return 0
        if ack.ack_code != AckCode.ACK_OK:
            raise LotError(
                f"MSCHED refused to unreserve {machine_id or 'the machines'} of entity {self.entity_id}: {ack.ack_code}"
            )
        self.log.info("unreserved %s (%s freed)", machine_id or "all machines", ack.freed)
        return int(ack.freed or 0)

    # ----------------------------------------------------------------- machines (WC)

    def recipe_for(self, machine_id: str, op_type: str) -> str:
        known = self._recipes.pop((machine_id, op_type), None)
        if known is not None:
            return known
        rows = self._query(
            "SELECT recipe_id FROM op_machine_recipe WHERE machine_id = %s AND op_type = %s ORDER BY recipe_id",
            machine_id,
            op_type,
        )
        if not rows:
            raise RunFailed(f"no recipe for {op_type} on {machine_id} in OP_MACHINE_RECIPE")
        return str(rows[0][0])

    def _read_recipes(self, op_type: str, machines: set[str]) -> None:
        """recipe_for each machine asked for, in one read while MSCHED decides: the ones bound need it next."""
        try:
            rows = self._query(
                "SELECT machine_id, min(recipe_id) FROM op_machine_recipe WHERE op_type = %s "
                "AND machine_id = ANY(%s) GROUP BY machine_id",
                op_type,
                sorted(machines),
            )
        except DatabaseError as e:  # recipe_for reads them again, and says so if it cannot
            self.log.warning("recipes for %s not read ahead: %s", op_type, e)
            return
        self._recipes = {(str(m), op_type): str(r) for m, r in rows}

    def setup_run(self, machine_id: str, recipe_id: str, op_type: str, machine_run_id: int) -> None:
        """SETUP_RUN to the machine's WC: recipe downloaded, machine set up (the CMM is homed first).

        Waits up to Timeouts.setup (the CMM waits for its start button), but no longer than the
        machine lives: MachineLost as soon as it goes Shutdown or its WC leaves the bus.
        """
        self.log.info("setting up run %d on %s with recipe %s", machine_run_id, machine_id, recipe_id)
        with self._cond:  # the run's life on this machine begins: what happens to it from now on counts
            self._began[(machine_id, machine_run_id)] = (time.monotonic(), self._peer_inc.get(f"wc:{machine_id}"))
        ack = self._ask_wc(
            "SETUP_RUN",
            message(
                "Setup_Run",
                machine_id=machine_id,
                recipe_id=recipe_id,
                op_type=op_type,
                machine_run_id=machine_run_id,
                entity_id=self.entity_id,
            ),
            machine_id,
            machine_run_id,
            self.timeouts.setup,
        )
        if ack.ack_code != AckCode.ACK_OK:
            self._raise_if_lost(machine_id, machine_run_id, ack)
            raise RunFailed(
                f"{machine_id} refused to set up run {machine_run_id} ({recipe_id}): {ack.ack_code}"
                + (f" ({ack.note})" if ack.note else "")
            )

    def start_run(self, machine_id: str, machine_run_id: int) -> None:
        """START_RUN to the machine's WC: run what was set up (MachineLost if the machine goes meanwhile)."""
        with self._cond:
            self._began.setdefault(
                (machine_id, machine_run_id), (time.monotonic(), self._peer_inc.get(f"wc:{machine_id}"))
            )
        ack = self._ask_wc(
            "START_RUN",
            message("Start_Run", machine_id=machine_id, machine_run_id=machine_run_id),
            machine_id,
            machine_run_id,
            self.timeouts.answer,
        )
        if ack.ack_code != AckCode.ACK_OK:
            self._raise_if_lost(machine_id, machine_run_id, ack)
            raise RunFailed(
                f"{machine_id} refused to start run {machine_run_id}: {ack.ack_code}"
                + (f" ({ack.note})" if ack.note else "")
            )
        self.log.info("run %d started on %s", machine_run_id, machine_id)

    def wait_run_complete(
        self, machine_run_id: int, machines: Sequence[str], timeout: float | None = None
    ) -> dict[str, str]:
        """Wait for RUN_COMPL of this run from every machine.

        A machine has left the run when, since the run began there, it went Shutdown, or Idle with no
        or another machine_run_id, or on to another run, and no RUN_COMPL followed within lost_grace.
        That it is up again by now (restarted by the operator) changes nothing: the status history
        remembers. A machine Idle after our run is how every run ends, a moment before its RUN_COMPL:
        that one gets `answer` to come. A machine that left the run may still have completed it: its
        WC stores the outcome in MACHINE_RUN_OUTCOME before it goes Idle, and may have died before its
        RUN_COMPL went out. So the outcome is read there, and only a run with none is lost (MachineLost).
        """
        started = time.monotonic()
        deadline = started + (timeout or self.timeouts.run)
        what = f"run {machine_run_id} to complete on " + ", ".join(machines)
        while True:
            done, by_machine = self._wait(
                lambda: self._run_ended(machine_run_id, machines, started),
                max(0.0, deadline - time.monotonic()),
                what,
                poll=lambda: self._read_status(machines, ENDED, machine_run_id),
            )
            if done:
                self.log.info(
                    "run %d complete: %s", machine_run_id, ", ".join(f"{m} {c}" for m, c in by_machine.items())
                )
                return by_machine
            outcomes = self._run_outcomes(machine_run_id, list(by_machine))
            with self._cond:
                for m, code in outcomes.items():
                    self.log.warning(
                        "run %d on %s: no RUN_COMPL came, MACHINE_RUN_OUTCOME says %s", machine_run_id, m, code
                    )
                    self._runs[(m, machine_run_id)] = code
            lost = [why for m, why in by_machine.items() if m not in outcomes]
            if lost:
                self.log.error("%s, and no RUN_COMPL followed nor is its outcome stored", lost[0])
                raise MachineLost(f"{lost[0]}: the run cannot complete")

    def _run_ended(
        self, machine_run_id: int, machines: Sequence[str], started: float
    ) -> tuple[bool, dict[str, str]] | None:
        """(under the lock) (True, machine -> ack code) once every machine's RUN_COMPL of the run came;
        (False, machine -> why) once some left the run without one; else None."""
        if all((m, machine_run_id) in self._runs for m in machines):
            return True, {m: self._runs[(m, machine_run_id)] for m in machines}
        now = time.monotonic()
        left: dict[str, str] = {}
        for m in machines:
            if (m, machine_run_id) in self._runs:
                continue
            since = self._began.get((m, machine_run_id), (started, None))[0]
            went = self._went(m, since, ENDED, machine_run_id)
            if went is None:
                continue
            when, status, run = went
            ended = status == MachineStatus.IDLE and run == machine_run_id
            grace = max(self.timeouts.lost_grace, self.timeouts.answer) if ended else self.timeouts.lost_grace
            if now - when > grace:
                other = f" (run {run})" if run != machine_run_id else ""
                left[m] = f"{m} went {status}{other} during run {machine_run_id}"
        return (False, left) if left else None

    def _run_outcomes(self, machine_run_id: int, machines: Sequence[str]) -> dict[str, str]:
        """machine -> ack code of the run as its WC stored it (MACHINE_RUN_OUTCOME); {} if unreadable."""
        try:
            rows = self._query(
                "SELECT machine_id, ack_code FROM machine_run_outcome WHERE machine_run_id = %s "
                "AND machine_id = ANY(%s)",
                machine_run_id,
                list(machines),
            )
        except DatabaseError as e:
            self.log.warning("could not read MACHINE_RUN_OUTCOME: %s", e)
            return {}
        return {str(m): str(code) for m, code in rows}

    def run_results(self, machine_id: str, machine_run_id: int) -> dict[str, str]:
        """The run's MACHINE_RUN_RESULT rows as param -> value."""
        rows = self._query(
            "SELECT param, value FROM machine_run_result WHERE machine_run_id = %s AND machine_id = %s ORDER BY param",
            machine_run_id,
            machine_id,
        )
        return {str(p): ("" if v is None else str(v)) for p, v in rows}

    def run_on(self, reservation: Reservation, recipes: str | dict[str, str] | None = None) -> list[Run]:
        """Set up and start the run on each reserved machine, wait for them all, read the results."""
        return self._results(reservation, *self._run(reservation, recipes))

    def _run(
        self, reservation: Reservation, recipes: str | dict[str, str] | None
    ) -> tuple[dict[str, str], dict[str, str]]:
        """run_on without reading the results: the recipe and the ack code of each machine's run."""
        run_id, op_type = reservation.machine_run_id, reservation.op_type
        chosen = {}
        for m in reservation.machines:
            recipe = recipes.get(m) if isinstance(recipes, dict) else recipes
            chosen[m] = recipe or self.recipe_for(m, op_type)
            self.setup_run(m, chosen[m], op_type, run_id)
            self.start_run(m, run_id)
        return chosen, self.wait_run_complete(run_id, reservation.machines)

    def _results(self, reservation: Reservation, chosen: dict[str, str], codes: dict[str, str]) -> list[Run]:
        run_id = reservation.machine_run_id
        return [Run(m, chosen[m], run_id, codes[m], self.run_results(m, run_id)) for m in reservation.machines]

    def operate(
        self,
        op_type: str,
        alternatives: Sequence[Sequence[str]] | None = None,
        recipes: str | dict[str, str] | None = None,
        priority: int | None = None,
    ) -> Operation:
        """One operation, start to end: reserve machines, run, unreserve, read the results (they are in
        the tables: the machines need not wait for the entity to read them).

        A machine lost (it shut down, its WC went silent or left, or it turned Idle without completing
        the run) is given back and the operation asked for again, up to `max_tries` times, each try
        after a pause (Timeouts.pause, doubling) and once a machine that can serve it is up; then
        MachineLost.
        """
        lost: MachineLost | None = None
        for attempt in range(1, self.max_tries + 1):
            if lost is not None:
                self._pause(attempt - 1, f"trying {op_type} again")
                self._wait_machine_up(op_type, alternatives, time.monotonic() + self.timeouts.machines)
            res = self.reserve(op_type, alternatives, priority)
            try:
                chosen, codes = self._run(res, recipes)
            except MachineLost as e:
                lost = e
                self.log.warning("%s (try %d of %d): unreserving and asking again", e, attempt, self.max_tries)
                self._record(op_type, res, [], f"machine lost: {e}")
                self.unreserve()
                continue
            self.unreserve()
            runs = self._results(res, chosen, codes)
            op = Operation(op_type, res.machine_run_id, runs, attempt)
            self._record(op_type, res, runs, verdict(op.results)[1] if op.ok else "run failed")
            return op
        raise MachineLost(f"{op_type}: {lost} ({self.max_tries} tries)")

    # ----------------------------------------------------------------- internals: bus

    def _present(self, name: str) -> bool:
        """Is `name` on the bus now (as this entity's bus last heard)?"""
        with self._cond:
            return name in self._peer_inc

    def _ask(
        self, cls: str, first: Message, to: str, timeout: float | None = None, within: float | None = None
    ) -> Message:
        """One conversation with a server (ls, msched): its answer.

        A server away from the bus, not started (Notnow "module not started": it is restarting) or
        silent past `timeout` is asked again, in a NEW conversation, after a pause (Timeouts.backoff,
        doubling to backoff_max) until `within` (Timeouts.retry) has passed; then LotTimeout. So every
        request sent through here must be safe to repeat (ENTITY_REQ, CANCEL_RE, UNRESERVE are).
        """
        if self._bus is None:
            raise LotError(f"entity {self.entity_id} is not open")
        backoff = Backoff(self.timeouts, within)
        while True:
            error: ConversationTimeout | None = None
            if not self._present(to):
                why = f"{to} is not on the bus"
            else:
                try:
                    conv, batch = self._bus.request(cls, first, to=to, timeout=timeout or self.timeouts.answer)
                except ConversationTimeout as e:
                    why, error = f"no answer within {timeout or self.timeouts.answer:.1f}s", e
                else:
                    conv.end()
                    if not _not_started(batch.first):
                        if backoff.tries:
                            self.log.info("%s answered %s after %d more tries", to, cls, backoff.tries)
                        return batch.first
                    why = f"{to} is not started (Notnow)"
            pause = backoff.next()
            if pause is None:
                self.log.error("%s to %s: %s; gave up after %d tries", cls, to, why, backoff.tries)
                raise LotTimeout(
                    f"entity {self.entity_id}: {cls} to {to} failed: {why} (asked {backoff.tries} times)"
                ) from error
            self.log.warning("%s to %s: %s; asking again in %.1fs", cls, to, why, pause)
            time.sleep(pause)

    def _ask_wc(self, cls: str, first: Message, machine_id: str, machine_run_id: int, timeout: float) -> Message:
        """One conversation with a machine's WC, given up (MachineLost) as soon as the machine is lost:
        it went Shutdown (UPD_ME_ST, or MACHINE_STATUS read meanwhile), or its WC left the bus for longer
        than lost_grace or came back as a new process (which knows nothing of this conversation) --
        rather than after the step's whole deadline. Never asked twice: a setup is not a repeatable step."""
        if self._bus is None:
            raise LotError(f"entity {self.entity_id} is not open")
        call = _Call()
        self._spawn(self._converse(call, self._bus.bus, cls, first, f"wc:{machine_id}", timeout))

        def answered() -> bool:
            if call.done:
                return True
            why = self._lost(machine_id, machine_run_id)
            if why:
                self.log.error("%s of run %d: %s; not waiting for wc:%s's answer", cls, machine_run_id, why, machine_id)
                raise MachineLost(f"{why} ({cls} of run {machine_run_id})")
            return False

        try:
            self._wait(
                answered,
                timeout + 1,
                f"wc:{machine_id}'s answer to {cls}",
                poll=lambda: self._read_status([machine_id], SHUT, None),
            )
        except BaseException:
            self._abandon(call)
            raise
        if call.error is not None:
            self._raise_if_lost(machine_id, machine_run_id, None)
            raise call.error
        assert call.answer is not None
        return call.answer

    async def _converse(self, call: _Call, bus: Bus, cls: str, first: Message, to: str, timeout: float) -> None:
        call.task = asyncio.current_task()
        if call.abandoned:
            return
        answer: Message | None = None
        error: GwcError | None = None
        try:
            conv, batch = await bus.request(cls, first, to=to, timeout=timeout)
            conv.end()
            answer = batch.first
        except GwcError as e:
            error = e
        with self._cond:
            call.answer, call.error, call.done = answer, error, True
            self._cond.notify_all()

    def _abandon(self, call: _Call) -> None:
        """Stop a conversation nobody waits for any more (its task ends it)."""
        call.abandoned = True
        if self._bus is not None:
            self._bus.call_soon(lambda: call.task.cancel() if call.task is not None else None)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run a coroutine on the bus's event loop (its thread), kept so close() can cancel it."""
        assert self._bus is not None

        def launch() -> None:
            task = asyncio.get_running_loop().create_task(coro)
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        self._bus.call_soon(launch)

    def _cancel_tasks(self) -> None:
        for t in list(self._tasks):
            t.cancel()

    async def _listen(self) -> None:
        """Broadcasts this entity listens to: RUN_COMPL, UPD_ME_ST, LOT_MOVED."""
        assert self._bus is not None
        bus = self._bus.bus
        while True:
            conv = await bus.first_message()
            if conv is None or conv.first is None:
                if bus.closed:
                    return
                continue
            conv.end()
            m = conv.first.first
            with self._cond:
                if m.name == "Run_Complete" and m.machine_run_id is not None:
                    self._runs[(m.machine_id, int(m.machine_run_id))] = m.ack_code
                elif m.name == "Update_ME_Status":
                    self._note(m.machine_id, m.status, m.machine_run_id)
                elif m.name == "Lot_Moved" and int(m.entity_id) == self.entity_id:
                    self._moved.append((m.action, m.lot_id))
                self._cond.notify_all()

    def _watch_peers(self, bus: Bus) -> None:
        """(bus thread) Keep who is on the bus, and since when a module left, for the steps that wait on one."""
        with self._cond:
            self._peer_inc.update({name: p.inc for name, p in bus.peers().items()})
        bus.peer_listeners.append(self._peer_changed)

    def _peer_changed(self, name: str, peer: Peer | None) -> None:
        with self._cond:
            if peer is None:
                self._peer_inc.pop(name, None)
                self._peer_left[name] = time.monotonic()
            else:
                self._peer_inc[name] = peer.inc
            self._cond.notify_all()

    async def _request(self, alt: _Alternative, priority: int | None) -> None:
        """One MACH_REQ conversation, from Machine_Request to its one Machine_Req_Comp.

        Until MSCHED takes it (Machine_Req_Ack), a MSCHED away, not started or silent is asked again
        in a new conversation, as `_ask` does: a request that did reach it and is asked again is one
        more alternative of the same alt_group, which MSCHED refuses once one is bound, and which the
        entity cancels once it has its machines.
        """
        assert self._bus is not None
        bus = self._bus.bus
        group = alt.group
        conv: Conversation | None = None
        backoff = Backoff(self.timeouts)
        try:
            while alt.ack is None and not alt.done:
                if group is not None and group.winner is not None:  # no need to ask any more
                    with self._cond:
                        alt.done = True
                        self._cond.notify_all()
                    return
                if not self._present("msched"):
                    why = "msched is not on the bus"
                else:
                    conv = await bus.start(
                        "MACH_REQ",
                        message(
                            "Machine_Request",
                            entity_id=self.entity_id,
                            op_type=alt.op_type,
                            num_machines=len(alt.machines),
                            priority=priority,
                            alt_group=group.alt_group if group else None,
                        ),
                        *[message("Machine_Entry", machine_id=m) for m in alt.machines],
                        to="msched",
                    )
                    try:
                        batch = await conv.next_message(self.timeouts.answer)
                    except ConversationTimeout:
                        why = f"no answer within {self.timeouts.answer:.1f}s"
                    else:
                        if not _not_started(batch.first):
                            await self._answered(alt, conv, batch)
                            continue
                        why = "msched is not started (Notnow)"
                    conv.end()
                    conv = None
                pause = backoff.next()
                if pause is None:
                    raise LotTimeout(
                        f"MACH_REQ for {alt.op_type} ({alt.describe()}): {why} (asked {backoff.tries} times)"
                    )
                self.log.warning(
                    "MACH_REQ for %s (%s): %s; asking again in %.1fs", alt.op_type, alt.describe(), why, pause
                )
                await asyncio.sleep(pause)
            while not alt.done:
                assert conv is not None
                await self._answered(alt, conv, await conv.next_message(FOREVER))
        except asyncio.CancelledError:
            raise
        except (GwcError, OSError) as e:
            with self._cond:
                alt.error = str(e)
                alt.done = True
                self._cond.notify_all()
        finally:
            if conv is not None:
                conv.end()

    async def _answered(self, alt: _Alternative, conv: Conversation, batch: Batch) -> None:
        """MSCHED's Machine_Req_Ack or Machine_Req_Comp for one alternative."""
        head = batch.first
        if head.name == "Machine_Req_Comp":
            await conv.send(message("Request_Comp_Ack", entity_id=self.entity_id, ack_code=AckCode.ACK_OK))
        with self._cond:
            if head.name == "Machine_Req_Ack":
                alt.ack = head
                alt.done = head.ack_code != AckCode.ACK_OK
            elif head.name == "Machine_Req_Comp":
                alt.comp = head
                alt.reserved = [m.machine_id for m in batch.messages[1:] if m.name == "Reserved_Machine"]
                alt.done = True
            taken = alt.group is not None and alt.group.winner not in (None, alt) and head.ack_code == AckCode.ACK_OK
            surplus = alt.group.surplus(alt) if taken and alt.group and head.name == "Machine_Req_Comp" else []
            queued = taken and head.name == "Machine_Req_Ack"
            self._cond.notify_all()
        for m in surplus:  # bound after the entity took another alternative: give it back
            self.log.warning("%s was bound after another alternative was taken: giving it back", m)
            await self._tell("UNRESERVE", message("Unreserve_Me", entity_id=self.entity_id, machine_id=m, by=self.name))
        if queued:  # queued after the entity took another alternative: it must not wait there
            self.log.warning("request %s was queued after another alternative was taken: cancelling it", alt.key)
            await self._tell("CANCEL_RE", message("Cancel_Request", request_key=alt.key, by=self.name))

    async def _tell(self, cls: str, first: Message) -> None:
        """(bus thread) A cleanup conversation with MSCHED whose answer only goes to the log."""
        assert self._bus is not None
        try:
            conv, batch = await self._bus.bus.request(cls, first, to="msched", timeout=self.timeouts.answer)
            conv.end()
            self.log.info("%s: %s", cls, batch.first.ack_code)
        except GwcError as e:
            self.log.error("%s failed: %s", cls, e)

    def _cancel_leftovers(self, when: str, request: MachineRequest | None = None) -> None:
        """Cancel the entity's requests still queued in MSCHED (all of them, or only `request`'s when
        another request of the entity is still being asked for). Belt and braces: a failure is logged."""
        try:
            if request is not None and any(r is not request for r in self._requests):
                n = sum(
                    self.cancel_requests(a.key, within=self.timeouts.cleanup)
                    for a in request.alternatives
                    if a.key is not None and not a.done and a is not request.winner
                )
            else:
                n = self.cancel_requests(within=self.timeouts.cleanup)
        except GwcError as e:
            self.log.warning("could not cancel the requests left %s: %s", when, e)
            return
        if n:
            self.log.info("cancelled %d request(s) of entity %d left queued %s", n, self.entity_id, when)

    # ----------------------------------------------------------------- internals: waiting

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

    def _wait_moved(self, action: str, states: Sequence[str], timeout: float) -> None:
        """Wait for LOT_MOVED(action) for this entity, reading LOT_STATUS as a fallback."""
        deadline = time.monotonic() + timeout
        while True:
            with self._cond:
                for act, lot_id in self._moved:
                    if act == action:
                        if lot_id is not None:
                            self.lot_id = lot_id
                        return
                self._cond.wait(min(POLL, max(0.0, deadline - time.monotonic())))
            state = self.read_state()
            if state in states:
                return
            if state == S.FAILED:
                raise LotError(f"entity {self.entity_id} was marked failed while waiting for {action}")
            if time.monotonic() > deadline:
                raise LotTimeout(
                    f"entity {self.entity_id}: the operator did not {action} the lot within "
                    f"{timeout:.0f}s (it is {state})"
                )

    def _wait_machine_up(self, op_type: str, alternatives: Sequence[Sequence[str]] | None, deadline: float) -> None:
        """Until a machine can serve the operation again: every machine of one alternative is up (without
        alternatives: one machine qualified for op_type is)."""
        while time.monotonic() < deadline:
            if alternatives:
                up = {
                    r[0] for r in self._query("SELECT machine_id FROM machine_status WHERE status = ANY(%s)", list(UP))
                }
                if any(a and set(a) <= up for a in alternatives):
                    return
            elif self.qualified_machines(op_type):
                return
            with self._cond:
                self._cond.wait(min(POLL, max(0.0, deadline - time.monotonic())))
        raise LotTimeout(f"entity {self.entity_id}: no machine for {op_type} came up in time")

    def _pause(self, tries: int, what: str) -> None:
        """The pause before an operation's next try: a machine that just failed gets time to be marked
        down (or come up) rather than be asked again at once."""
        pause = self.timeouts.pause * 2 ** (tries - 1)
        self.log.info("%s in %.1fs", what, pause)
        time.sleep(pause)

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

    def _lost(self, machine_id: str, machine_run_id: int) -> str | None:
        """(under the lock) Why the machine's WC will not answer for this run any more, if it will not."""
        since, inc = self._began.get((machine_id, machine_run_id), (time.monotonic(), None))
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

    # ----------------------------------------------------------------- internals: database, record

    def _db(self) -> psycopg.Connection[Any]:
        if self._conn is None or self._conn.closed:
            self._conn = db.connect(self.cfg, role="lot", log=self.log)
        return self._conn

    def _query(self, sql: str, *params: Any) -> list[tuple[Any, ...]]:
        return db.transaction(self._db, lambda cur: cur.execute(sql, params).fetchall(), log=self.log)

    def _query_one(self, sql: str, *params: Any) -> tuple[Any, ...] | None:
        rows = self._query(sql, *params)
        return rows[0] if rows else None

    def _read_lot(self) -> None:
        row = self._query_one(
            "SELECT s.state, s.lot_id, l.product_id, l.priority, l.work_order_id FROM lot_status s "
            "JOIN lots l USING (lot_id) WHERE s.entity_id = %s",
            self.entity_id,
        )
        if row is None:
            raise LotError(f"unknown lot entity {self.entity_id}: the Lot Server has no LOT_STATUS row for it")
        self._set_state(row[0])
        self.lot_id, self.product_id, self.priority, self.work_order_id = row[1], row[2], row[3], row[4]

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
                "at": _now(),
            }
        )
        self._save()

    def _save(self) -> None:
        """Write the traveller (var/lots/entity-E.json) atomically; it is a record, never required."""
        try:
            path = traveller_path(self.cfg, self.entity_id)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.traveller, default=str, indent=1))
            tmp.replace(path)
        except OSError as e:
            self.log.warning("could not write the traveller: %s", e)


def traveller_path(cfg: Config, entity_id: int) -> Path:
    return cfg.var / "lots" / f"entity-{entity_id}.json"


def read_traveller(cfg: Config, entity_id: int) -> dict[str, Any] | None:
    try:
        return json.loads(traveller_path(cfg, entity_id).read_text())
    except (OSError, ValueError):
        return None


def _now() -> str:
    return datetime.now().isoformat(" ", "milliseconds")


def _reason(exc: BaseException) -> str:
    if isinstance(exc, (GwcError, BusError)):
        return str(exc)
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted"
    return f"lot script error: {type(exc).__name__}: {exc}"


def create_lot(
    bus: BlockingBus,
    product_id: str,
    quantity: int,
    *,
    work_order_id: int | None = None,
    owner: str | None = None,
    priority: int | None = None,
    script_id: str | None = None,
    lot_type: str | None = None,
    timeout: float = 10.0,
    within: float = 60.0,
    request_id: str | None = None,
) -> tuple[int, list[int]]:
    """CREATE_LOT: ask the Lot Server for a lot of `quantity` entities. Returns (lot_id, entity_ids).

    A Lot Server that does not answer (it died after creating the lot, or is restarting) is asked
    again for up to `within` seconds with the same request_id, so the lot is made once: a repeat is
    answered with what the first request made. Give request_id to make it survive this call too.
    """
    request_id = request_id or f"{bus.bus.name}.{secrets.token_hex(8)}"
    ack = bus.run(
        ask(
            bus.bus,
            "CREATE_LOT",
            message(
                "Create_Lot_Entity",
                product_id=product_id,
                quantity=quantity,
                work_order_id=work_order_id,
                owner=owner,
                priority=priority,
                script_id=script_id,
                lot_type=lot_type,
                request_id=request_id,
            ),
            "ls",
            timeout,
            within=within,
        )
    )
    if ack.ack_code != AckCode.ACK_OK or ack.lot_id is None:
        raise LotError(
            f"the Lot Server refused to create a lot of {quantity} {product_id}: {ack.ack_code}"
            + (f" ({ack.note})" if ack.note else "")
        )
    return int(ack.lot_id), [int(e) for e in ack.entity_ids or []]


__all__ = [
    "MachineRequest",
    "Operation",
    "OperationEntity",
    "Reservation",
    "Run",
    "ScriptStopped",
    "Timeouts",
    "create_lot",
    "read_traveller",
    "traveller_path",
    "verdict",
]
