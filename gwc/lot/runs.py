"""The operation entity and the machines' WCs (MachineRuns): recipes, SETUP_RUN, START_RUN, waiting for
RUN_COMPL (or finding the machine lost, or its run in doubt), and the run's results (see
gwc/lot/entity.py, docs/lot-scripts.md)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence

from gwc.errors import DatabaseError, GwcError
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, LotState, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.lot.core import Heard, LotReads
from gwc.lot.errors import MachineDied, MachineLost, RunFailed, RunInDoubt
from gwc.lot.lot_server import LotServerLink
from gwc.lot.model import ENDED, RELEASES, SHUT, UP, Reservation, Run, WcCall, now_text
from gwc.lot.state import EntityState
from gwc.lot.talk import BusLink
from gwc.retry import Deadline


class MachineRuns:
    """A reserved machine's run, step by step; one conversation with a machine's WC (`ask_wc`)."""

    def __init__(self, facts: EntityState, reads: LotReads, heard: Heard, link: BusLink, ls: LotServerLink) -> None:
        self.facts = facts
        self.reads = reads
        self.heard = heard
        self.link = link
        self.ls = ls

    def recipe_for(self, machine_id: str, op_type: str) -> str:
        """The machine's recipe for the op type (OP_MACHINE_RECIPE, the first by name): the one its WC
        sets up when a SETUP_RUN names none."""
        rows = self.reads.query(
            "SELECT recipe_id FROM op_machine_recipe WHERE machine_id = %s AND op_type = %s ORDER BY recipe_id",
            machine_id,
            op_type,
        )
        if not rows:
            raise RunFailed(f"no recipe for {op_type} on {machine_id} in OP_MACHINE_RECIPE")
        return str(rows[0][0])

    def setup_run(
        self, machine_id: str, recipe_id: str | None, op_type: str, machine_run_id: int, start: bool = False
    ) -> str:
        """SETUP_RUN to the machine's WC: recipe downloaded, machine set up (the CMM is homed first).
        With no recipe_id the WC sets up its machine's recipe for the op type (recipe_for); returns the
        recipe set up. With `start` the WC also starts the run once it is set up (START_RUN's work in the
        same conversation: one round trip to the WC fewer), so a lost answer leaves the run in doubt,
        as start_run's does.

        Waits up to Timeouts.setup (the CMM waits for its start button), but no longer than the
        machine lives: MachineLost as soon as it goes Shutdown or its WC leaves the bus.
        """
        self.facts.log.info(
            "setting up%s run %d on %s with recipe %s",
            " and starting" if start else "",
            machine_run_id,
            machine_id,
            recipe_id or "(its own)",
        )
        msg = message(
            Msg.SETUP_RUN,
            machine_id=machine_id,
            recipe_id=recipe_id,
            op_type=op_type,
            machine_run_id=machine_run_id,
            entity_id=self.facts.entity_id,
            start=start or None,
        )
        if start:
            timeout = self.facts.timeouts.setup + self.facts.timeouts.answer
            ack = self._ask_wc_to_start(Conv.SETUP_RUN, msg, machine_id, machine_run_id, timeout, begins=True)
            if ack is None:
                return recipe_id or self.recipe_for(machine_id, op_type)
        else:
            self._begin(machine_id, machine_run_id, anew=True)
            ack = self.ask_wc(Conv.SETUP_RUN, msg, machine_id, machine_run_id, self.facts.timeouts.setup)
        if ack.ack_code != AckCode.ACK_OK:
            self.raise_if_lost(machine_id, machine_run_id, ack)
            raise RunFailed(
                f"{machine_id} refused to set up{' and start' if start else ''} run {machine_run_id} "
                f"({recipe_id or op_type}): {ack.ack_code}" + (f" ({ack.note})" if ack.note else "")
            )
        if start:
            self.facts.log.info("run %d started on %s", machine_run_id, machine_id)
        return str(ack.recipe_id or recipe_id or "")  # (a WC names the recipe it set up)

    def start_run(self, machine_id: str, machine_run_id: int) -> None:
        """START_RUN to the machine's WC: run what was set up (MachineLost if the machine goes meanwhile)."""
        ack = self._ask_wc_to_start(
            Conv.START_RUN,
            message(Msg.START_RUN, machine_id=machine_id, machine_run_id=machine_run_id),
            machine_id,
            machine_run_id,
            self.facts.timeouts.answer,
        )
        if ack is None:
            return
        if ack.ack_code != AckCode.ACK_OK:
            self.raise_if_lost(machine_id, machine_run_id, ack)
            raise RunFailed(
                f"{machine_id} refused to start run {machine_run_id}: {ack.ack_code}"
                + (f" ({ack.note})" if ack.note else "")
            )
        self.facts.log.info("run %d started on %s", machine_run_id, machine_id)

    def _begin(self, machine_id: str, machine_run_id: int, anew: bool) -> float:
        """The run's life on the machine begins now (anew: with this setup; else unless its setup began
        it): what happens to the machine from then on counts for the run. Returns now."""
        self.link.watch([machine_id])  # (bound, so heard since the binding: unless resumed, or bound unheard)
        return self.heard.begin(machine_id, machine_run_id, anew)

    def _ask_wc_to_start(
        self, cls: str, first: Message, machine_id: str, machine_run_id: int, timeout: float, begins: bool = False
    ) -> Message | None:
        """A conversation whose answer says the run started (START_RUN, or SETUP_RUN with start). A
        machine that goes Shutdown unheard (no death known) before the answer may have started the run
        all the same (its WC froze after telling the ME): None, the run in doubt, waited for as such
        (wait_run_complete), never given up and run elsewhere blindly. `begins`: the run's life on the
        machine begins with this conversation (a setup's), see _begin."""
        started = self._begin(machine_id, machine_run_id, anew=begins)
        try:
            return self.ask_wc(cls, first, machine_id, machine_run_id, timeout)
        except MachineLost as e:
            with self.heard.cond:
                doubt = self._doubt_since(machine_id, machine_run_id, started) is not None
            if not doubt:
                raise
            self.facts.log.warning(
                "%s of run %d unanswered (%s): it may have started: in doubt", cls, machine_run_id, e
            )
            return None

    def wait_run_complete(
        self, machine_run_id: int, machines: Sequence[str], timeout: float | None = None
    ) -> dict[str, str]:
        """Wait for RUN_COMPL of this run from every machine.

        A machine has left the run when, since the run began there, its ME died (its agent said so:
        the run is lost for certain, MachineDied, after `death_settle`), or it went Idle with no or
        another machine_run_id, or on to another run, or up again after a Shutdown, and no RUN_COMPL
        followed within lost_grace. That it is up again by now changes nothing: the status history
        remembers. A machine Idle after our run is how every run ends, a moment before its RUN_COMPL:
        that one gets `answer` to come. A machine that left the run may still have completed it: its
        WC stores the outcome in MACHINE_RUN_OUTCOME before it goes Idle, and may have died before its
        RUN_COMPL went out. So the outcome is read there, and only a run with none is lost (MachineLost).

        A machine that went Shutdown and stays so, with no death known, only cannot be heard (its WC
        silent: frozen, cut off, or dead where no agent runs): its run is **in doubt**, not lost. The
        entity waits for its RUN_COMPL or stored outcome (read every POLL) or a death, until the run's
        expected time (cell.toml `run_time` of the machine) plus Timeouts.in_doubt from its start;
        then the lot script decides (`in_doubt`): hold (the default) or reroute. Never run again blindly.
        """
        started = time.monotonic()
        deadline = Deadline(timeout or self.facts.timeouts.run)
        what = f"run {machine_run_id} to complete on " + ", ".join(machines)
        while True:
            done, by_machine = self.heard.wait(
                lambda: self._run_ended(machine_run_id, machines, started),
                deadline.left(),
                what,
                poll=lambda: self._poll_run(machine_run_id, machines, started),
            )
            if done:
                self.facts.log.info(
                    "run %d complete: %s", machine_run_id, ", ".join(f"{m} {c}" for m, c in by_machine.items())
                )
                return by_machine
            outcomes = self.run_outcomes(machine_run_id, list(by_machine))
            with self.heard.cond:
                for m, code in outcomes.items():
                    self.facts.log.warning(
                        "run %d on %s: no RUN_COMPL came, MACHINE_RUN_OUTCOME says %s", machine_run_id, m, code
                    )
                    self.heard.runs[(m, machine_run_id)] = code
            lost = [m for m in by_machine if m not in outcomes]
            if lost:
                why = by_machine[lost[0]]
                with self.heard.cond:
                    doubt = any(self._doubt_since(m, machine_run_id, started) is not None for m in lost)
                    died = all(self._run_death(m, machine_run_id, started) for m in lost)
                if doubt and self._decide_in_doubt(lost[0], machine_run_id, why):
                    continue  # held, and the run completed meanwhile: it counts
                self.facts.log.error("%s, and no RUN_COMPL followed nor is its outcome stored", why)
                raise (MachineDied if died else MachineLost)(f"{why}: the run cannot complete")

    def _run_ended(
        self, machine_run_id: int, machines: Sequence[str], started: float
    ) -> tuple[bool, dict[str, str]] | None:
        """(under the lock) (True, machine -> ack code) once every machine's RUN_COMPL of the run came;
        (False, machine -> why) once some left the run without one, or its doubt outlived its bound;
        else None."""
        if all((m, machine_run_id) in self.heard.runs for m in machines):
            return True, {m: self.heard.runs[(m, machine_run_id)] for m in machines}
        now = time.monotonic()
        left: dict[str, str] = {}
        for m in machines:
            if (m, machine_run_id) in self.heard.runs:
                continue
            died = self._run_death(m, machine_run_id, started)
            if died is not None:  # known for certain: no grace, only the moment its WC needs to settle
                if now - died[0] >= self.facts.timeouts.death_settle:
                    left[m] = f"me:{m} died ({died[1]}) during run {machine_run_id}"
                continue
            shut = self._doubt_since(m, machine_run_id, started)
            if shut is not None:
                bound = self._doubt_bound(m, machine_run_id, started)
                if now > bound:
                    left[m] = (
                        f"{m} went Shutdown during run {machine_run_id} and has not been heard of since "
                        f"({now - shut:.0f}s; the run's bound is {bound - shut:.0f}s after that)"
                    )
                continue
            since = self.heard.began.get((m, machine_run_id), (started, None))[0]
            went = self.heard.went(m, since, ENDED, machine_run_id)
            if went is None:
                continue
            when, status, run = went
            ended = status == MachineStatus.IDLE and run == machine_run_id
            grace = (
                max(self.facts.timeouts.lost_grace, self.facts.timeouts.answer)
                if ended
                else self.facts.timeouts.lost_grace
            )
            if now - when > grace:
                other = f" (run {run})" if run != machine_run_id else ""
                left[m] = f"{m} went {status}{other} during run {machine_run_id}"
        return (False, left) if left else None

    def _doubt_since(self, machine_id: str, machine_run_id: int, started: float) -> float | None:
        """(under the lock) When the machine went Shutdown during the run, if it is Shutdown still (not up
        again, not on another run) with no death known: the run is in doubt since then; else None."""
        since = self.heard.began.get((machine_id, machine_run_id), (started, None))[0]
        went = self.heard.went(machine_id, since, SHUT)
        if went is None or self._run_death(machine_id, machine_run_id, started) is not None:
            return None
        last = self.heard.history[machine_id][-1]
        if last[1] not in SHUT or (last[2] is not None and last[2] != machine_run_id):
            return None
        return went[0]

    def _doubt_bound(self, machine_id: str, machine_run_id: int, started: float) -> float:
        """The moment a run in doubt is given up on: its expected time after it began, plus in_doubt."""
        began = self.heard.began.get((machine_id, machine_run_id), (started, None))[0]
        try:
            expected = float(self.facts.cfg.machine(machine_id).options.get("run_time", 0.0))
        except (GwcError, TypeError, ValueError):
            expected = 0.0
        return began + expected + self.facts.timeouts.in_doubt

    def _poll_run(self, machine_run_id: int, machines: Sequence[str], started: float) -> None:
        """The wait's fallback reads: MACHINE_STATUS, and for a run in doubt MACHINE_RUN_OUTCOME (a WC that
        was frozen stores the run when it wakes, though its machine stays Shutdown)."""
        self.read_status(machines, ENDED, machine_run_id)
        with self.heard.cond:
            doubted = [
                m
                for m in machines
                if (m, machine_run_id) not in self.heard.runs
                and self._doubt_since(m, machine_run_id, started) is not None
            ]
        if not doubted:
            return
        outcomes = self.run_outcomes(machine_run_id, doubted)
        with self.heard.cond:
            for m, code in outcomes.items():
                self.facts.log.warning(
                    "run %d on %s was in doubt: MACHINE_RUN_OUTCOME says %s", machine_run_id, m, code
                )
                self.heard.runs[(m, machine_run_id)] = code
            self.heard.cond.notify_all()

    def _decide_in_doubt(self, machine_id: str, machine_run_id: int, why: str) -> bool:
        """The run's doubt outlived its bound: the lot script's decision (`in_doubt`), logged and kept in
        the traveller. reroute (or retry): MachineLost, so the operation is asked for again; hold (the
        default): the entity is held (LOT_STATUS held, shown to the operator) until the operator
        releases it (retry, reroute: MachineLost; fail: RunInDoubt) or the run completes after all
        (True: it counts)."""
        decision = self.facts.in_doubt
        self.facts.log.error(
            "run %d on %s is in doubt (%s): the lot script decides: %s", machine_run_id, machine_id, why, decision
        )
        self._decided(machine_run_id, machine_id, why, decision)
        if decision == "hold":
            decision = self._hold(machine_id, machine_run_id, why)
            if decision == "completed":
                return True
        if decision in ("reroute", "retry"):
            raise MachineLost(f"{why}: in doubt, {decision} by the lot script's or the operator's decision")
        raise RunInDoubt(
            f"{why}: in doubt, released as failed by the operator (if the run completes on {machine_id} it is "
            "recorded, not run again)"
        )

    def _decided(self, machine_run_id: int, machine_id: str, why: str, decision: str) -> None:
        self.facts.traveller.setdefault("decisions", []).append(
            {
                "machine_run_id": machine_run_id,
                "machine": machine_id,
                "why": why,
                "decision": decision,
                "at": now_text(),
            }
        )
        self.facts.save()

    def _hold(self, machine_id: str, machine_run_id: int, why: str) -> str:
        """Held for the operator (LOT_STATUS held, `gwc release`): the machines stay reserved, the run is
        still listened for. Returns the operator's decision (RELEASES), or "completed" if the run's
        RUN_COMPL or stored outcome came first."""
        with self.heard.cond:
            seen = len(self.heard.moved)  # a release is a LOT_MOVED from now on
        self.ls.entity_request("held", reason=f"{why}: in doubt, held for the operator"[:500])
        self.facts.set_state(LotState.HELD)
        self.facts.save()
        self.facts.log.error(
            "entity %d held for the operator: `gwc release %d --decision retry|reroute|fail`",
            self.facts.entity_id,
            self.facts.entity_id,
        )

        def released() -> str | None:
            if (machine_id, machine_run_id) in self.heard.runs:
                return "completed"
            return next((act for act, _ in self.heard.moved[seen:] if act in RELEASES), None)

        def poll() -> None:
            self._poll_run(machine_run_id, [machine_id], time.monotonic())
            state = self.ls.read_state()
            with self.heard.cond:
                if state == LotState.FAILED:
                    self.heard.moved.append(("fail", None))
                elif state not in (LotState.HELD, None):
                    self.heard.moved.append(("retry", None))
                self.heard.cond.notify_all()

        decision = self.heard.wait(
            released, self.facts.timeouts.held, "the operator to release the held entity", poll=poll
        )
        self.facts.log.warning("held entity %d: %s", self.facts.entity_id, decision)
        self._decided(machine_run_id, machine_id, why, f"released: {decision}")
        if decision != "fail":
            self.ls.report(LotState.RUNNING)
        return decision

    def _run_death(self, machine_id: str, machine_run_id: int, started: float) -> tuple[float, str] | None:
        """(under the lock) The ME death an agent announced since the run began on the machine."""
        return self.heard.died(
            f"me:{machine_id}", self.heard.began.get((machine_id, machine_run_id), (started, None))[0]
        )

    def run_outcomes(self, machine_run_id: int, machines: Sequence[str]) -> dict[str, str]:
        """machine -> ack code of the run as its WC stored it (MACHINE_RUN_OUTCOME); {} if unreadable."""
        try:
            rows = self.reads.query(
                "SELECT machine_id, ack_code FROM machine_run_outcome WHERE machine_run_id = %s "
                "AND machine_id = ANY(%s)",
                machine_run_id,
                list(machines),
            )
        except DatabaseError as e:
            self.facts.log.warning("could not read MACHINE_RUN_OUTCOME: %s", e)
            return {}
        return {str(m): str(code) for m, code in rows}

    def run_results(self, machine_id: str, machine_run_id: int) -> dict[str, str]:
        """The run's MACHINE_RUN_RESULT rows as param -> value: as they came with its Run_Complete (a WC
        sends small ones along, as stored), else read from the table."""
        with self.heard.cond:
            came = self.heard.results.get((machine_id, machine_run_id))
        if came is not None:
            return dict(sorted(came.items()))
        rows = self.reads.query(
            "SELECT param, value FROM machine_run_result WHERE machine_run_id = %s AND machine_id = %s ORDER BY param",
            machine_run_id,
            machine_id,
        )
        return {str(p): ("" if v is None else str(v)) for p, v in rows}

    def run_on(self, reservation: Reservation, recipes: str | dict[str, str] | None = None) -> list[Run]:
        """Set up and start the run on each reserved machine, wait for them all, read the results."""
        return self.results(reservation, *self.run(reservation, recipes))

    def run(
        self,
        reservation: Reservation,
        recipes: str | dict[str, str] | None,
        todo: dict[str, str] | None = None,
    ) -> tuple[dict[str, str], dict[str, str]]:
        """run_on without reading the results: the recipe and the ack code of each machine's run. A run
        a restarted script takes up is set up, started or only waited for on each machine as `todo`
        says ("setup", "start", "wait": as far as it went there, resume.py)."""
        run_id, op_type = reservation.machine_run_id, reservation.op_type
        chosen = {}
        for m in reservation.machines:
            recipe = recipes.get(m) if isinstance(recipes, dict) else recipes
            step = (todo or {}).get(m, "setup")
            if step == "setup":
                chosen[m] = self.setup_run(m, recipe, op_type, run_id, start=True)
                continue
            chosen[m] = recipe or self.recipe_for(m, op_type)
            if step == "start":
                self.start_run(m, run_id)
        return chosen, self.wait_run_complete(run_id, reservation.machines)

    def results(self, reservation: Reservation, chosen: dict[str, str], codes: dict[str, str]) -> list[Run]:
        run_id = reservation.machine_run_id
        failed = [m for m in reservation.machines if codes[m] != AckCode.ACK_OK]
        notes = self._run_notes(run_id, failed) if failed else {}
        runs = []
        for m in reservation.machines:
            results = self.run_results(m, run_id)
            runs.append(Run(m, chosen[m], run_id, codes[m], results, notes.get(m) or results.get("NOTE", "")))
        return runs

    def _run_notes(self, machine_run_id: int, machines: Sequence[str]) -> dict[str, str]:
        """machine -> why its run failed, as its WC stored it (MACHINE_RUN_OUTCOME's note)."""
        rows = self.reads.query(
            "SELECT machine_id, note FROM machine_run_outcome WHERE machine_run_id = %s AND machine_id = ANY(%s)",
            machine_run_id,
            list(machines),
        )
        return {str(m): str(note) for m, note in rows if note}

    # ----------------------------------------------------------------- a WC's answer

    def ask_wc(self, cls: str, first: Message, machine_id: str, machine_run_id: int, timeout: float) -> Message:
        """One conversation with a machine's WC, given up (MachineLost) as soon as the machine is lost:
        it went Shutdown (UPD_ME_ST, or MACHINE_STATUS read meanwhile), or its WC left the bus for longer
        than lost_grace or came back as a new process (which knows nothing of this conversation) --
        rather than after the step's whole deadline. Never asked twice: a setup is not a repeatable step."""
        call = WcCall()
        self.link.spawn(self._converse(call, self.link.need().bus, cls, first, f"wc:{machine_id}", timeout))

        def answered() -> bool:
            if call.done:
                return True
            why = self.heard.lost(machine_id, machine_run_id)
            if why:
                self.facts.log.error(
                    "%s of run %d: %s; not waiting for wc:%s's answer", cls, machine_run_id, why, machine_id
                )
                raise MachineLost(f"{why} ({cls} of run {machine_run_id})")
            return False

        try:
            self.heard.wait(
                answered,
                timeout + 1,
                f"wc:{machine_id}'s answer to {cls}",
                poll=lambda: self.read_status([machine_id], SHUT, None),
            )
        except BaseException:
            self._abandon(call)
            raise
        if call.error is not None:
            self.raise_if_lost(machine_id, machine_run_id, None)
            raise call.error
        assert call.answer is not None
        return call.answer

    async def _converse(self, call: WcCall, bus: Bus, cls: str, first: Message, to: str, timeout: float) -> None:
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
        with self.heard.cond:
            call.answer, call.error, call.done = answer, error, True
            self.heard.cond.notify_all()

    def _abandon(self, call: WcCall) -> None:
        """Stop a conversation nobody waits for any more (its task ends it)."""
        call.abandoned = True
        self.link.call_soon(lambda: call.task.cancel() if call.task is not None else None)

    def read_status(self, machines: Sequence[str], statuses: Sequence[str], machine_run_id: int | None) -> None:
        """Fallback for a missed UPD_ME_ST: a machine found in one of `statuses` (or, if machine_run_id is
        given, on another run) in MACHINE_STATUS is noted as having changed now."""
        try:
            rows = self.reads.query(
                "SELECT machine_id, status, machine_run_id FROM machine_status WHERE machine_id = ANY(%s)",
                list(machines),
                within=0,
            )
        except DatabaseError as e:
            self.facts.log.warning("could not read MACHINE_STATUS: %s", e)
            return
        with self.heard.cond:
            for m, status, run in rows:
                other = machine_run_id is not None and run is not None and run != machine_run_id
                known = self.heard.history.get(m)
                if (status in statuses or other) and not (known and known[-1][1:] == (status, run)):
                    self.facts.log.info("%s is %s (run %s) in MACHINE_STATUS", m, status, run)
                    self.heard.note(m, status, run)
                    self.heard.cond.notify_all()

    def raise_if_lost(self, machine_id: str, machine_run_id: int, ack: Message | None) -> None:
        """A refusal (or no answer) because the machine is going or gone loses the machine: it shut down
        since the run began there, its WC left or restarted, it is not up now, or it cannot serve now."""
        with self.heard.cond:
            why = self.heard.lost(machine_id, machine_run_id)
        if why:
            raise MachineLost(why)
        row = self.reads.query_one("SELECT status FROM machine_status WHERE machine_id = %s", machine_id)
        if row is None or row[0] not in UP:
            raise MachineLost(f"{machine_id} is {row[0] if row else 'unknown'}")
        if ack is not None and ack.ack_code == AckCode.NOTNOW:
            raise MachineLost(f"{machine_id} cannot serve now ({ack.note or ack.ack_code})")
