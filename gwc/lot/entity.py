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

The entity listens to RUN_COMPL (its runs finish) and UPD_ME_ST (a reserved machine shut down mid-run:
the step is retried, after a pause, on whatever machine is up, a bounded number of times) about the
machines bound to it only, from the binding until it gives them back (docs/protocol.md, *Subjects*),
and to MOD_DIED once its lot is in the cell (imported), so that lots are not woken by other lots'
runs. The operator's import and export of it (LOT_MOVED) the Lot Server sends to it alone. It
remembers every status change of the machines it works with, so a machine that went Shutdown and came
up again while the entity waited is still known to have lost the run. Servers come and go too: a
conversation with the Lot Server or MSCHED that finds it away, restarting or not yet started is asked
again with a backoff for a bounded time (Timeouts.retry); every request the entity repeats that way is
safe to repeat.

It reads the tables (as role gwc_lot) and writes none but its own record. Besides its log it keeps a
traveller, var/lots/entity-E.json: what it ran where and what it decided, for the operator (`gwc lots
show E`), the demonstration and its own resume after a kill; in a cell over several hosts also in
LOT_TRAVELLERS, so that a script started on another host when this one's died resumes from it
(gwc/lothosts.py).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Sequence
from typing import Any

from gwc import lothosts as hosting
from gwc.config import Config
from gwc.errors import GwcError
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message
from gwc.ipc.codes import LotState
from gwc.lot.core import Heard, LotReads
from gwc.lot.errors import MachineDied, MachineLost, ScriptStopped
from gwc.lot.holdings import Holdings, create_lot
from gwc.lot.lot_server import LotServerLink
from gwc.lot.model import (
    IMPORTED,
    MachineRequest,
    Operation,
    Reservation,
    Run,
    Timeouts,
    failure_reason,
    forget_previous_traveller,
    now_text,
    read_traveller,
    traveller_path,
    verdict,
)
from gwc.lot.reserve import MachineRequests
from gwc.lot.resume import Resumption
from gwc.lot.runs import MachineRuns, Sheets
from gwc.lot.state import EntityState, Shared
from gwc.lot.talk import BusLink
from gwc.retry import Deadline


class OperationEntity:
    """One operation entity: a lot script's handle on the cell (see the module docstring).

    It holds its parts, each with its own small interface: the entity's state (EntityState: who it is,
    what the Lot Server said, the script's settings, the traveller), its reads of the tables (LotReads),
    what it has heard of the cell and the waits on it (Heard), its bus (BusLink), the Lot Server
    (LotServerLink), MSCHED (MachineRequests), the machines' WCs (MachineRuns), a restarted script's
    record (Resumption), and recipes, scrap and children (Holdings). Here: its life, Listing 1's
    steps, and the lot script's calls, each handed to the part that does it.
    """

    # The entity's state as attributes of its own (read and set by lot scripts): EntityState's fields.
    cfg: Shared[Config] = Shared()
    entity_id: Shared[int] = Shared()
    log: Shared[logging.Logger] = Shared()
    timeouts: Shared[Timeouts] = Shared()
    max_tries: Shared[int] = Shared()
    in_doubt: Shared[str] = Shared()
    lot_id: Shared[int | None] = Shared()
    state: Shared[str | None] = Shared()
    product_id: Shared[str | None] = Shared()
    priority: Shared[int | None] = Shared()
    work_order_id: Shared[int | None] = Shared()
    script_id: Shared[str | None] = Shared()
    script_path: Shared[str | None] = Shared()
    result: Shared[str | None] = Shared()
    traveller: Shared[dict[str, Any]] = Shared()
    name: Shared[str] = Shared()
    _bus: Shared[BlockingBus | None] = Shared("link", "blocking")  # (a test's lot script reaches for it)

    def __init__(
        self, cfg: Config, entity_id: int, log: logging.Logger, timeouts: Timeouts | None = None, max_tries: int = 3
    ) -> None:
        self.facts = EntityState(cfg, entity_id, log, timeouts or Timeouts(), max_tries)
        self.reads = LotReads(self.facts)
        self.heard = Heard(self.facts)
        self.link = BusLink(self.facts, self.heard)
        self.ls = LotServerLink(self.facts, self.heard, self.link)
        self.requests = MachineRequests(self.facts, self.reads, self.heard, self.link, self.ls)
        self.runs = MachineRuns(self.facts, self.reads, self.heard, self.link, self.ls)
        self.resume = Resumption(self.facts, self.reads, self.heard, self.link, self.requests, self.runs)
        self.holdings = Holdings(self.facts, self.link, self.runs)
        if hosting.hosted(cfg):  # the traveller in the database too: a script on another host resumes from it
            self.facts.keep = hosting.TravellerStore(cfg, self.facts.entity_id, self.reads, log)

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
            if self.facts.state in (LotState.COMPLETED, LotState.WAITING_EXPORT, LotState.EXPORTED):
                if exc is not None:  # its work is done: the lot stays as it is, the operator exports it
                    self.facts.log.warning(
                        "lot script of entity %d stopped after its lot completed (%s): entity stays %s",
                        self.facts.entity_id,
                        failure_reason(exc),
                        self.facts.state,
                    )
            elif exc is not None:
                self.fail(failure_reason(exc))
            elif self.facts.state != LotState.FAILED:
                self.fail("the lot script ended without completing its lot")
        finally:
            self.close()

    def open(self) -> None:
        """Join the bus as lot:E, attach to the Lot Server (ENTITY_REQ attach, our pid), which answers with
        the entity's state, lot and lot script, and listen."""
        self.link.open()
        self.ls.open()
        ack = self.ls.attach()
        if self.facts.state in IMPORTED:
            self.link.listen_in_cell()
        self.facts.log.info(
            "entity %d attached (lot %s, product %s, state %s, pid %d)",
            self.facts.entity_id,
            self.lot_id,
            self.product_id,
            ack.state,
            os.getpid(),
        )
        self.resume.after_restart()
        self.facts.traveller.update(
            lot_id=self.lot_id,
            product_id=self.product_id,
            pid=os.getpid(),
            host=self.facts.cfg.host,
            started=now_text(),
            state=self.facts.state,
        )
        self.facts.save()

    def close(self) -> None:
        """Leave the bus and the database. Safe to call twice."""
        self.ls.close()
        self.link.close()
        self.reads.release()
        forget_previous_traveller(self.facts.cfg, self.facts.entity_id)

    def fail(self, reason: str) -> None:
        """Give back everything and mark the entity failed: requests cancelled, machines unreserved."""
        if self.facts.failed:
            return
        self.facts.failed = True
        self.facts.log.error("entity %d failed: %s; cleaning up", self.facts.entity_id, reason)
        self.facts.traveller.update(result=f"failed: {reason}")
        if self.link.blocking is None:
            return
        if self.link.present("msched"):
            for what, fn in (("cancel its requests", self.cancel_requests), ("unreserve its machines", self.unreserve)):
                try:
                    fn(timeout=self.facts.timeouts.cleanup)
                except GwcError as e:
                    self.facts.log.error("cleanup: could not %s: %s", what, e)
        else:
            self.facts.log.error("cleanup: msched is not on the bus; its reaper cleans up when it returns")
        with contextlib.suppress(GwcError):  # a refused report is why we fail, perhaps: the failure still goes
            self.ls.drain_reports()
        try:  # asked again while the Lot Server is away (Timeouts.retry): else the entity stays as it is
            self.ls.entity_request("failed", reason=reason[:500], timeout=self.facts.timeouts.cleanup)
        except GwcError as e:
            self.facts.log.error("cleanup: the Lot Server did not take the failure: %s", e)
        self.facts.set_state(LotState.FAILED)
        self.facts.save()

    # ----------------------------------------------------------------- Listing 1

    def wait_for_import(self, timeout: float | None = None) -> None:
        """Ask to be imported and wait for the operator's IMPORT_LOT (Listing 1's wait_for_import)."""
        state = self.facts.state  # from the attach, and changed since only by our requests and the operator's moves
        if state in IMPORTED:
            self.facts.log.info("entity %d already imported (%s)", self.facts.entity_id, state)
        else:
            if state != LotState.WAITING_IMPORT:
                self.ls.entity_request("import")  # imported ahead by the operator meanwhile: ALREADY
            if self.facts.state not in IMPORTED:
                self.facts.log.info("entity %d waiting to be imported", self.facts.entity_id)
                self.ls.wait_moved("import", IMPORTED, timeout or self.facts.timeouts.import_)
            self.facts.set_state(LotState.IMPORTED)
            self.facts.log.info("entity %d imported (lot %s)", self.facts.entity_id, self.lot_id)
        self.link.listen_in_cell()

    def lot_completed(self, result: str | None = None) -> None:
        """Tell the Lot Server the lot's work here is done, with its result (Listing 1's lot_completed).

        First every request of the entity that may still be queued in MSCHED is cancelled: nothing may
        wait for machines on behalf of a finished entity. (A request MSCHED has ended, bound or refused,
        needs no CANCEL_RE; a dead process's were cancelled when this one took the entity up.)
        """
        if self.facts.state in (LotState.COMPLETED, LotState.WAITING_EXPORT):  # a restarted script: done before
            self.facts.log.info("entity %d completed already (%s)", self.facts.entity_id, self.facts.result)
            return
        if self.requests.may_be_queued():
            self.requests.cancel_leftovers("before completing")
        self.ls.entity_request("completed", reason=result)
        self.facts.result = result
        self.facts.traveller.update(result=result or "completed")
        self.facts.log.info("entity %d completed: %s", self.facts.entity_id, result or "done")
        self.facts.save()

    def wait_for_export(self, timeout: float | None = None) -> None:
        """Ask to be exported and wait for the operator's EXPORT_LOT (Listing 1's wait_for_export)."""
        state = self.facts.state
        if state != LotState.EXPORTED:
            if state != LotState.WAITING_EXPORT:
                self.ls.entity_request("export", reason=self.facts.result)  # the Lot Server keeps it as the reason
            self.facts.log.info("entity %d waiting to be exported", self.facts.entity_id)
            self.ls.wait_moved("export", (LotState.EXPORTED,), timeout or self.facts.timeouts.export)
        self.facts.set_state(LotState.EXPORTED)
        self.facts.save()
        self.facts.log.info("entity %d exported (lot %s)", self.facts.entity_id, self.lot_id)

    def operate(
        self,
        op_type: str,
        alternatives: Sequence[Sequence[str]] | None = None,
        recipes: str | dict[str, str] | None = None,
        priority: int | None = None,
        sheet: Sheets | None = None,
    ) -> Operation:
        """One operation, start to end: reserve machines, run, unreserve, read the results (they are in
        the tables: the machines need not wait for the entity to read them).

        A machine lost (it shut down, its WC went silent or left, or it turned Idle without completing
        the run) is given back and the operation asked for again, up to `max_tries` times, each try
        after a pause (Timeouts.pause, doubling) and once a machine that can serve it is up; then
        MachineLost. A machine whose ME's death its agent announced (MachineDied) is known to be out of
        service already (its machine is Shutdown), so the next try goes without the pause.

        In a lot script restarted after its process was killed, an operation done before is not done
        again and one whose run was under way is taken up where it is (gwc/lot/resume.py).
        `sheet(machine, recipe)`: each run's sheet of offsets (gwc/quality), asked once the machine is known.
        """
        step, entry, resumed = self.resume.point(op_type)
        if isinstance(resumed, Operation):
            return resumed
        lost: MachineLost | None = None
        for attempt in range(int(entry["tries"]) if entry else 1, self.facts.max_tries + 1):
            if lost is not None and not isinstance(lost, MachineDied):
                self.requests.pause(attempt - 1, f"trying {op_type} again")
                self.requests.wait_machine_up(op_type, alternatives, Deadline(self.facts.timeouts.machines))
            res, taken_up, resumed = resumed or self.requests.reserve(op_type, alternatives, priority), resumed, None
            if taken_up is None:
                self.resume.record_step(step, res, recipes, attempt, None)
            try:
                todo = (
                    None if taken_up is None else {m: self.resume.take_up(m, res.machine_run_id) for m in res.machines}
                )
                chosen, codes = self.runs.run(res, recipes, todo, sheet)
            except MachineLost as e:
                lost = e
                self.facts.log.warning(
                    "%s (try %d of %d): unreserving and asking again", e, attempt, self.facts.max_tries
                )
                self.facts.record(op_type, res, [], f"machine lost: {e}")
                self.unreserve()
                continue
            # The results are read and the operation recorded while MSCHED frees the machines. A script
            # restarted after the record gives back what is still reserved for a done run (resume.py).
            freeing = self.requests.unreserve_soon()
            try:
                runs = self.runs.results(res, chosen, codes)
                self.resume.record_step(step, res, chosen, attempt, codes, save=False)  # saved by _record
                op = Operation(op_type, res.machine_run_id, runs, attempt)
                self.facts.record(op_type, res, runs, verdict(op.results)[1] if op.ok else "run failed")
            finally:
                freeing()
            return op
        raise MachineLost(f"{op_type}: {lost} ({self.facts.max_tries} tries)")

    # ----------------------------------------------------------------- the Lot Server

    def entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
    ) -> Message:
        """ENTITY_REQ: ask the Lot Server to move this entity (LotServerLink.entity_request)."""
        return self.ls.entity_request(action, reason, script_pid, timeout, within)

    def read_state(self) -> str | None:
        """The entity's state as the Lot Server has it, asked once (LotServerLink.read_state)."""
        return self.ls.read_state()

    def report(self, action: str) -> None:
        """A progress state (waiting_machine, running) sent in the background (LotServerLink.report)."""
        self.ls.report(action)

    # ----------------------------------------------------------------- MSCHED

    def qualified_machines(self, op_type: str, up_only: bool = True) -> list[str]:
        """Machines with a recipe for op_type (OP_MACHINE_RECIPE), those that are up if `up_only`."""
        return self.requests.qualified_machines(op_type, up_only)

    def request_machines(
        self, op_type: str, alternatives: Sequence[Sequence[str]], priority: int | None = None
    ) -> MachineRequest:
        """MACH_REQ: one request per alternative (MachineRequests.request_machines)."""
        return self.requests.request_machines(op_type, alternatives, priority)

    def wait_for_machines(self, request: MachineRequest, timeout: float | None = None) -> Reservation:
        """Wait for MSCHED to bind one alternative (MachineRequests.wait_for_machines)."""
        return self.requests.wait_for_machines(request, timeout)

    def reserve(
        self,
        op_type: str,
        alternatives: Sequence[Sequence[str]] | None = None,
        priority: int | None = None,
        timeout: float | None = None,
    ) -> Reservation:
        """Request machines and wait for them, asking again when none can serve now (MachineRequests.reserve)."""
        return self.requests.reserve(op_type, alternatives, priority, timeout)

    def cancel_requests(
        self, request_key: int | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """CANCEL_RE: cancel one request, or all of the entity's. Returns how many were cancelled."""
        return self.requests.cancel_requests(request_key, timeout, within)

    def unreserve(
        self, machine_id: str | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """UNRESERVE: free one reserved machine, or all of the entity's. Returns how many were freed."""
        return self.requests.unreserve(machine_id, timeout, within)

    def unreserve_soon(
        self, machine_id: str | None = None, timeout: float | None = None, within: float | None = None
    ) -> Callable[[], int]:
        """unreserve() sent now; call the function returned for MSCHED's answer (how many were freed)."""
        return self.requests.unreserve_soon(machine_id, timeout, within)

    # ----------------------------------------------------------------- the machines' WCs

    def recipe_for(self, machine_id: str, op_type: str) -> str:
        """The machine's recipe for the op type (MachineRuns.recipe_for)."""
        return self.runs.recipe_for(machine_id, op_type)

    def setup_run(
        self, machine_id: str, recipe_id: str | None, op_type: str, machine_run_id: int, start: bool = False
    ) -> str:
        """SETUP_RUN to the machine's WC (and START_RUN's work with `start`): the recipe set up."""
        return self.runs.setup_run(machine_id, recipe_id, op_type, machine_run_id, start)

    def start_run(self, machine_id: str, machine_run_id: int) -> None:
        """START_RUN to the machine's WC: run what was set up (MachineLost if the machine goes meanwhile)."""
        self.runs.start_run(machine_id, machine_run_id)

    def wait_run_complete(
        self, machine_run_id: int, machines: Sequence[str], timeout: float | None = None
    ) -> dict[str, str]:
        """Wait for RUN_COMPL of this run from every machine (MachineRuns.wait_run_complete)."""
        return self.runs.wait_run_complete(machine_run_id, machines, timeout)

    def run_results(self, machine_id: str, machine_run_id: int) -> dict[str, str]:
        """The run's MACHINE_RUN_RESULT rows as param -> value."""
        return self.runs.run_results(machine_id, machine_run_id)

    def run_on(self, reservation: Reservation, recipes: str | dict[str, str] | None = None) -> list[Run]:
        """Set up and start the run on each reserved machine, wait for them all, read the results."""
        return self.runs.results(reservation, *self.runs.run(reservation, recipes))

    # ----------------------------------------------------------------- recipes, scrap, children

    def download_recipe(self, machine_id: str, recipe_id: str) -> None:
        """Listing 1's ers_download (Holdings.download_recipe)."""
        self.holdings.download_recipe(machine_id, recipe_id)

    def upload_recipe(self, machine_id: str, recipe_id: str) -> int:
        """Listing 1's ers_upload (Holdings.upload_recipe): the version stored."""
        return self.holdings.upload_recipe(machine_id, recipe_id)

    def propose_recipe(self, recipe_id: str, content: str) -> int:
        """RECIPE_PUT to the ERS: a new, unapproved version of the recipe (Holdings.propose_recipe)."""
        return self.holdings.propose_recipe(recipe_id, content)

    def scrap(self, machine_id: str, machine_run_id: int, parts: int = 1, reason: str | None = None) -> None:
        """SCRAP_RPT to the Machine Server: parts of that run are scrap (Holdings.scrap)."""
        self.holdings.scrap(machine_id, machine_run_id, parts, reason)

    def start_child(self, product_id: str, quantity: int = 1, script_id: str | None = None) -> list[int]:
        """Start child operation entities in a new lot (Holdings.start_child): their entity ids."""
        return self.holdings.start_child(product_id, quantity, script_id)

    def divide(self, quantity: int = 1, start_scripts: bool = True) -> list[int]:
        """The Lot Server's division (Holdings.divide): the new entities."""
        return self.holdings.divide(quantity, start_scripts)

    def merge(self, child: int) -> None:
        """The Lot Server's merger of a child into this entity (Holdings.merge)."""
        self.holdings.merge(child)

    def wait_for_children(self, children: Sequence[int], timeout: float | None = None) -> dict[int, str]:
        """Wait until every child is done (Holdings.wait_for_children): each one's state."""
        return self.holdings.wait_for_children(children, timeout)

    def raise_alarm(self, alarm_id: str, machine_id: str, text: str) -> int | None:
        """ALARM_SEND in the lot's name (Holdings.raise_alarm: quality's SPC_RULE, TOOL_CHANGE): its number."""
        return self.holdings.raise_alarm(alarm_id, machine_id, text)

    def read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        """Rows of a read of the tables, asked again while the database is away (LotReads.read)."""
        return self.reads.read(sql, params)


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
