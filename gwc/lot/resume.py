"""A lot script restarted after its process was killed resumes its entity from what is stored.

Its host's agent restarts a lot script that dies of a signal (kill -9, a crash of the interpreter):
the new process runs the script's `main(entity)` from the start, and the entity makes the repeat
harmless. Every `operate()` is an operation step, numbered in the order the script asks for them;
the step's record in the traveller (var/lots/entity-E.json, `operations`) is written when its machines
are bound (the machine_run_id, before any SETUP_RUN) and again when it is done (each machine's ack
code). What happened to the run is the database's: MACHINE_RUN_OUTCOME (the WC stores it before its
Run_Complete), RESERVED_MACHINES and MACHINE_STATUS. So, for step n of the restarted script:

* done before the restart, or its run's outcome stored by every machine since: not run again; the
  Operation is rebuilt from the stored outcome and MACHINE_RUN_RESULT (a run completed since is
  settled, its machines given back, as soon as the new process has attached: `_settle_completed`);
* bound and still reserved: the run is taken up where it is: waited for while Running (or in doubt,
  its machine Shutdown unheard: the ordinary rules for a run in doubt), started if set up, set up and
  started if not begun;
* anything else (its machines given back after a lost run, or never bound): asked for anew.

A script is deterministic given what its operations returned, so it asks for the same operations in
the same order; one that asks for another op type than its record has at that step gets no more
replays (logged). At the new process's start, requests the dead one left queued are cancelled and
machines it was bound that no step's record names (bound after its last record was written, so never
set up) are given back. Only `operate()` resumes: a script made of the lower-level calls starts over.
"""

from __future__ import annotations

import os
from typing import Any

from gwc.errors import GwcError
from gwc.ipc.codes import LotState, MachineStatus
from gwc.lot.core import Heard, LotReads
from gwc.lot.model import Operation, Reservation, Run, read_traveller
from gwc.lot.reserve import MachineRequests
from gwc.lot.runs import MachineRuns
from gwc.lot.state import EntityState
from gwc.lot.talk import BusLink

RUNNING = (MachineStatus.RUNNING.value, MachineStatus.RUN_SHUT.value)
SET_UP = (MachineStatus.SETUP.value, MachineStatus.SETUP_SHUT.value)


class Resumption:
    """The operation steps' record, and taking a killed script's entity up again from it."""

    def __init__(
        self,
        facts: EntityState,
        reads: LotReads,
        heard: Heard,
        link: BusLink,
        requests: MachineRequests,
        runs: MachineRuns,
    ) -> None:
        self.facts = facts
        self.reads = reads
        self.heard = heard
        self.link = link
        self.requests = requests
        self.runs = runs
        self._step = 0  # the next operation step of this process
        self._replay: list[dict[str, Any]] | None = None  # the steps a dead process of this entity recorded

    def after_restart(self) -> None:
        """(at open, attached) A traveller of another process of this entity: take its record over, and
        clean up what the dead process left in MSCHED that no record names."""
        keep = self.facts.keep  # a hosted cell: the record in the database, whichever host wrote it
        old = keep.read() if keep is not None else None
        old = old or read_traveller(self.facts.cfg, self.facts.entity_id)
        # Completed and waiting to be exported too: its operations are replayed, not asked for again.
        mine = old is not None and old.get("pid") == os.getpid() and old.get("host") == self.facts.cfg.host
        if not old or old.get("pid") is None or mine or self.facts.state is None:
            return
        self._replay = list(old.get("operations") or [])
        self.facts.traveller.update(old)
        self.facts.traveller["restarts"] = int(old.get("restarts") or 0) + 1
        self.facts.result = old.get("result")
        self.facts.log.warning(
            "entity %d resumes after its lot script (pid %s%s) ended: %d operation(s) recorded",
            self.facts.entity_id,
            old.get("pid"),
            f" on {old['host']}" if old.get("host") and old.get("host") != self.facts.cfg.host else "",
            len(self._replay),
        )
        if self.facts.state in (LotState.CREATED, LotState.WAITING_IMPORT):
            return  # it had asked MSCHED for nothing yet
        self.requests.cancel_leftovers("by the dead script")
        open_runs = {int(op["machine_run_id"]) for op in self._replay if op.get("codes") is None}
        for machine_id, run in self.reads.query(
            "SELECT machine_id, machine_run_id FROM reserved_machines WHERE entity_id = %s", self.facts.entity_id
        ):
            if int(run) not in open_runs:
                self.facts.log.warning(
                    "%s was bound (run %s) after the dead script's last record: giving it back", machine_id, run
                )
                try:
                    self.requests.unreserve(machine_id, within=self.facts.timeouts.cleanup)
                except GwcError as e:
                    self.facts.log.error("could not give %s back: %s", machine_id, e)
        self._settle_completed()

    def _settle_completed(self) -> None:
        """(at open) A recorded run whose outcome every machine stored while no script ran is settled now,
        before the script's own first steps (its reads for the operation's choices): its codes recorded,
        its machines given back. Production may be waiting for them (a host lost: every machine held by
        its dead scripts); the script replays the step as done when it comes to it (`point`)."""
        for entry in self._replay or []:
            if entry.get("codes") is not None:
                continue
            run, machines = int(entry["machine_run_id"]), list(entry["machines"])
            codes = self.runs.run_outcomes(run, machines)
            if len(codes) != len(machines):
                continue
            op_type = entry.get("op_type")
            self.facts.log.warning("run %d of %s completed while the lot script was down: %s", run, op_type, codes)
            entry["codes"] = codes
            held = self.reads.query(
                "SELECT machine_id FROM reserved_machines WHERE entity_id = %s AND machine_run_id = %s",
                self.facts.entity_id,
                run,
            )
            for (machine_id,) in held:
                try:
                    self.requests.unreserve(machine_id, within=self.facts.timeouts.cleanup)
                except GwcError as e:
                    self.facts.log.error("could not give %s back: %s", machine_id, e)

    def point(self, op_type: str) -> tuple[int, dict[str, Any] | None, Operation | Reservation | None]:
        """This operation's step, its record from a dead process (if any), and what is left of it: the
        Operation if it was done, the Reservation if its run is to be taken up, else None."""
        step, self._step = self._step, self._step + 1
        if self._replay is None or step >= len(self._replay):
            return step, None, None
        entry = self._replay[step]
        if entry.get("op_type") != op_type:
            self.facts.log.error(
                "the script asks for %s at operation %d, where its record has %s: no more replays",
                op_type,
                step + 1,
                entry.get("op_type"),
            )
            self._replay = None
            return step, None, None
        run, machines = int(entry["machine_run_id"]), list(entry["machines"])
        codes = entry.get("codes")
        if codes is None:
            codes = self.runs.run_outcomes(run, machines)
            if len(codes) == len(machines):  # it completed while no script ran: the run counts
                self.facts.log.warning("run %d of %s completed while the lot script was down: %s", run, op_type, codes)
                self.requests.unreserve(within=self.facts.timeouts.cleanup)
                entry["codes"] = codes
                self.facts.save()
            else:
                codes = None
        if codes is not None:
            runs = [Run(m, self._recipe(entry, m), run, str(codes[m]), self.runs.run_results(m, run)) for m in machines]
            self.facts.log.info(
                "operation %d (%s) was done before the restart: run %d on %s, not run again",
                step + 1,
                op_type,
                run,
                ", ".join(machines),
            )
            return step, entry, Operation(op_type, run, runs, int(entry.get("tries") or 1))
        held = {
            r[0]
            for r in self.reads.query(
                "SELECT machine_id FROM reserved_machines WHERE entity_id = %s AND machine_run_id = %s",
                self.facts.entity_id,
                run,
            )
        }
        if held == set(machines):
            self.facts.log.warning(
                "operation %d (%s): run %d on %s is taken up where it is", step + 1, op_type, run, ", ".join(machines)
            )
            self.link.watch(machines)
            return step, entry, Reservation(op_type, run, entry.get("request_key"), machines)
        if held:
            self.requests.unreserve(within=self.facts.timeouts.cleanup)
        self.facts.log.warning(
            "operation %d (%s): run %d was given up before the restart: asking again", step + 1, op_type, run
        )
        return step, entry, None

    def _recipe(self, entry: dict[str, Any], machine_id: str) -> str:
        recipes = entry.get("recipes")
        recipe = recipes.get(machine_id) if isinstance(recipes, dict) else recipes
        return str(recipe or self.runs.recipe_for(machine_id, entry["op_type"]))

    def record_step(
        self, step: int, res: Reservation, recipes: Any, tries: int, codes: dict[str, str] | None, save: bool = True
    ) -> None:
        """The step's record: bound (codes None: written before its first SETUP_RUN), or done (saved with
        the operation's own record: a restart between the two finds the run's outcome stored anyway)."""
        ops: list[dict[str, Any]] = self.facts.traveller.setdefault("operations", [])
        entry = {
            "op_type": res.op_type,
            "machine_run_id": res.machine_run_id,
            "request_key": res.request_key,
            "machines": res.machines,
            "recipes": recipes,
            "tries": tries,
            "codes": codes,
        }
        ops[step:] = [entry]
        if self._replay is not None:
            self._replay[step : step + 1] = [entry]
        if save:
            self.facts.save()

    def take_up(self, machine_id: str, machine_run_id: int) -> str:
        """(a resumed run) What is left to do on the machine: "wait" (Running, or Shutdown with the run:
        in doubt), "start" (set up for it) or "setup" (not begun there)."""
        row = self.reads.query_one(
            "SELECT status, machine_run_id FROM machine_status WHERE machine_id = %s", machine_id
        )
        status, run = (row[0], row[1]) if row else (None, None)
        if run is None or int(run) != machine_run_id or status not in (*RUNNING, *SET_UP, MachineStatus.SHUTDOWN.value):
            return "setup"
        self.heard.begin(machine_id, machine_run_id)
        with self.heard.cond:
            if status == MachineStatus.SHUTDOWN.value:
                self.heard.note(machine_id, status, machine_run_id)
        self.facts.log.info("run %d is %s on %s", machine_run_id, status, machine_id)
        return "start" if status in SET_UP else "wait"
