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

It reads the tables (as role gwc_lot) and writes none. Besides its log it keeps a traveller,
var/lots/entity-E.json: what it ran where and what it decided, for the operator (`gwc lots show E`)
and the demonstration.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import secrets
import time
from collections.abc import Sequence
from typing import Any

from gwc.errors import GwcError
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.lot.errors import LotError, MachineDied, MachineLost, ScriptStopped
from gwc.lot.model import (
    IMPORTED,
    WAITING_LISTENS,
    MachineRequest,
    Operation,
    Reservation,
    Run,
    S,
    Timeouts,
    failure_reason,
    forget_previous_traveller,
    now_text,
    read_traveller,
    traveller_path,
    verdict,
)
from gwc.lot.resume import EntityResume
from gwc.lot.runs import Sheets
from gwc.module import ask


class OperationEntity(EntityResume):
    """One operation entity: a lot script's handle on the cell (see the module docstring).

    Its parts, by concern: EntityCore (state, reads, waits), EntityTalk (the bus, the Lot Server),
    EntityReserve (MSCHED), EntityRuns (the machines' WCs), EntityResume (a restarted script taking its
    entity up again); here its life and Listing 1's steps.
    """

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
                        failure_reason(exc),
                        self.state,
                    )
            elif exc is not None:
                self.fail(failure_reason(exc))
            elif self.state != S.FAILED:
                self.fail("the lot script ended without completing its lot")
        finally:
            self.close()

    def open(self) -> None:
        """Join the bus as lot:E, attach to the Lot Server (ENTITY_REQ attach, our pid), which answers with
        the entity's state, lot and lot script, and listen."""
        # A lot talks to servers and WCs, never to another lot: it does not track the other lot scripts
        # (their beats, hellos and byes are dropped before it wakes), nor answer their queries. It hears
        # the machines' news once it is in the cell (_listen_in_cell).
        self._bus = BlockingBus(self.name, self.cfg.bus, self.log, interest=WAITING_LISTENS, ignored_peers=("lot:",))
        self._bus.call_soon(self._watch_peers, self._bus.bus)
        self._bus.peers()  # returns after _watch_peers ran (the bus thread runs callbacks in order)
        self._spawn(self._listen())
        # Started now, not at the first report: starting a thread takes milliseconds on a busy machine.
        self._reporter = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"{self.name}-reports")
        self._reporter.submit(lambda: None)
        ack = self._attach()
        if self.state in IMPORTED:
            self._listen_in_cell()
        self.log.info(
            "entity %d attached (lot %s, product %s, state %s, pid %d)",
            self.entity_id,
            self.lot_id,
            self.product_id,
            ack.state,
            os.getpid(),
        )
        self._resume_after_restart()
        self.traveller.update(
            lot_id=self.lot_id, product_id=self.product_id, pid=os.getpid(), started=now_text(), state=self.state
        )
        self._save()

    def close(self) -> None:
        """Leave the bus and the database. Safe to call twice."""
        if self._reporter is not None:  # a report still retrying fails fast once the bus is gone
            self._reporter.shutdown(wait=False, cancel_futures=True)
            self._reporter = None
        if self._bus is not None:
            bus, self._bus = self._bus, None
            if self._heard_about:  # its own machines' only (docs/protocol.md, "Subjects")
                heard = ", ".join(f"{m} {n}" for m, n in sorted(self._heard_about.items()))
                self.log.info("machine news heard (UPD_ME_ST, RUN_COMPL): %s", heard)
            bus.call_soon(self._cancel_tasks)
            with contextlib.suppress(Exception):
                bus.close()
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
            self._conn = None
        forget_previous_traveller(self.cfg, self.entity_id)

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

    # ----------------------------------------------------------------- Listing 1

    def wait_for_import(self, timeout: float | None = None) -> None:
        """Ask to be imported and wait for the operator's IMPORT_LOT (Listing 1's wait_for_import)."""
        state = self.state  # from the attach, and changed since only by our requests and the operator's moves
        if state in IMPORTED:
            self.log.info("entity %d already imported (%s)", self.entity_id, state)
        else:
            if state != S.WAITING_IMPORT:
                self.entity_request("import")  # imported ahead by the operator meanwhile: ALREADY
            if self.state not in IMPORTED:
                self.log.info("entity %d waiting to be imported", self.entity_id)
                self._wait_moved("import", IMPORTED, timeout or self.timeouts.import_)
            self._set_state(S.IMPORTED)
            self.log.info("entity %d imported (lot %s)", self.entity_id, self.lot_id)
        self._listen_in_cell()

    def lot_completed(self, result: str | None = None) -> None:
        """Tell the Lot Server the lot's work here is done, with its result (Listing 1's lot_completed).

        First every request of the entity that may still be queued in MSCHED is cancelled: nothing may
        wait for machines on behalf of a finished entity. (A request MSCHED has ended, bound or refused,
        needs no CANCEL_RE; a dead process's were cancelled when this one took the entity up.)
        """
        if self.state in (S.COMPLETED, S.WAITING_EXPORT):  # a restarted script: done before
            self.log.info("entity %d completed already (%s)", self.entity_id, self.result)
            return
        if self._may_be_queued():
            self._cancel_leftovers("before completing")
        self.entity_request("completed", reason=result)
        self.result = result
        self.traveller.update(result=result or "completed")
        self.log.info("entity %d completed: %s", self.entity_id, result or "done")
        self._save()

    def wait_for_export(self, timeout: float | None = None) -> None:
        """Ask to be exported and wait for the operator's EXPORT_LOT (Listing 1's wait_for_export)."""
        state = self.state
        if state != S.EXPORTED:
            if state != S.WAITING_EXPORT:
                self.entity_request("export", reason=self.result)  # the Lot Server keeps it as the reason
            self.log.info("entity %d waiting to be exported", self.entity_id)
            self._wait_moved("export", (S.EXPORTED,), timeout or self.timeouts.export)
        self._set_state(S.EXPORTED)
        self._save()
        self.log.info("entity %d exported (lot %s)", self.entity_id, self.lot_id)

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
        step, entry, resumed = self._resume_point(op_type)
        if isinstance(resumed, Operation):
            return resumed
        lost: MachineLost | None = None
        for attempt in range(int(entry["tries"]) if entry else 1, self.max_tries + 1):
            if lost is not None and not isinstance(lost, MachineDied):
                self._pause(attempt - 1, f"trying {op_type} again")
                self._wait_machine_up(op_type, alternatives, time.monotonic() + self.timeouts.machines)
            res, taken_up, resumed = resumed or self.reserve(op_type, alternatives, priority), resumed, None
            if taken_up is None:
                self._record_step(step, res, recipes, attempt, None)
            try:
                todo = None if taken_up is None else {m: self._take_up(m, res.machine_run_id) for m in res.machines}
                chosen, codes = self._run(res, recipes, todo, sheet)
            except MachineLost as e:
                lost = e
                self.log.warning("%s (try %d of %d): unreserving and asking again", e, attempt, self.max_tries)
                self._record(op_type, res, [], f"machine lost: {e}")
                self.unreserve()
                continue
            # The results are read and the operation recorded while MSCHED frees the machines. A script
            # restarted after the record gives back what is still reserved for a done run (resume.py).
            freeing = self.unreserve_soon()
            try:
                runs = self._results(res, chosen, codes)
                self._record_step(step, res, chosen, attempt, codes, save=False)  # saved by _record
                op = Operation(op_type, res.machine_run_id, runs, attempt)
                self._record(op_type, res, runs, verdict(op.results)[1] if op.ok else "run failed")
            finally:
                freeing()
            return op
        raise MachineLost(f"{op_type}: {lost} ({self.max_tries} tries)")


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
            Conv.CREATE_LOT,
            message(
                Msg.CREATE_LOT_ENTITY,
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
