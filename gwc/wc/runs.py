"""The WC and its ME: requests over the queue pair, what the ME sends on its own (alarms, run
completions), a dead ME, and the end of a run: results stored, status, Run_Complete (see gwc/wc/wc.py)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

from gwc.db import Statement
from gwc.errors import ConversationTimeout, DatabaseError, DatabaseUnavailable, GwcError, QueueError
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import MeMessage, MessageId
from gwc.ipc.names import Conv, Msg
from gwc.me import answer_deadline
from gwc.me.results import read_outcome, read_results
from gwc.module import DATABASE_OUTAGE_S
from gwc.wc.base import ALL_OPERATIONS, SERVER_TIMEOUT, S, WCBase
from gwc.wc.link import MeDied

# A run's results ride in its Run_Complete when they are this small (characters of params and values
# together), so that its lot need not read them back; larger ones only in MACHINE_RUN_RESULT.
INLINE_RESULTS = 2000
# Whose run it is: the lot its Run_Complete must reach, named to the bus (a WC does not track lot scripts).
_RUN_LOT = "SELECT entity_id FROM reserved_machines WHERE machine_id = %(m)s AND machine_run_id = %(run)s"


def _lot(row: tuple[Any, ...] | None) -> str | None:
    return None if row is None or row[0] is None else f"lot:{row[0]}"


START_CANCELLED = "start cancelled: the machine was stopped before it was homed and started"


class StartCancelled(GwcError):
    """ME_START was cancelled by a stop (ME_SHUT) while it waited for the machine to be homed."""


class WCRuns(WCBase):
    """The ME side and a run's end."""

    _starting: asyncio.Future[None] | None = None  # ME_START is out to the ME: done once it is answered
    _start_cancelled: str | None = None  # why the ME_START out was cancelled (a stop came), once it was
    _start_alarms: set[int]  # the alarms (HOME_CMM) raised while that ME_START is out

    # ----------------------------------------------------------------- the ME side

    def _from_me(self, msg: MeMessage) -> None:
        """What the ME sends on its own: an alarm, or the end of a run."""
        if msg.message_id == MessageId.CELL_ALAR:
            self._spawn(self.alarm_action(msg))
        else:
            self._spawn(self.run_complete(msg))

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = self._loop.create_task(self._guard(coro))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _guard(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run work the ME started: log its failure, never lose it silently."""
        try:
            await coro
        except asyncio.CancelledError:
            raise
        except DatabaseUnavailable as e:
            self.log.error("work on a message from the ME failed: %s", e)
        except Exception:
            self.log.exception("work on a message from the ME failed")

    async def me_request(self, msg: MeMessage, timeout: float | None = None) -> MeMessage:
        """One request to the ME, waited for `timeout` or as long as this machine's ME may take
        (gwc.me.answer_deadline); the wait stays open while an alarm of ours waits for the operator."""
        wait = timeout if timeout is not None else answer_deadline(self.cfg.machine(self.machine_id))
        return await self.me.request(msg, wait, hold_open=lambda: self._alarm_pending > 0)

    async def me_died(self, why: str) -> None:
        """6.3's ME is gone: alarm, a run in progress failed, machine Shutdown until the next ME_START.

        A run whose results file the ME wrote before it died (its RUN_COMPL read by a WC that died
        too) is completed from the file instead.
        """
        self.log.error("ME of %s is dead (%s): alarm, machine Shutdown", self.machine_id, why)
        run_id = self.machine_run_id if self.status in (S.RUNNING, S.RUN_SHUT) else None
        await self.raise_alarm("ME_DIED", f"machine side of {self.machine_id} stopped answering: {why}", wait=False)
        if run_id is not None and self._results_path(run_id).exists():
            path = self._results_path(run_id)
            self.log.warning("run %d ended before the ME died: completing it from its results file %s", run_id, path)
            code, note = self._outcome_in(path)
            await self._finish_run(run_id, code, path, note, shutdown=f"ME died: {why}", tell_me=False)
            return
        await self._go_shutdown(f"ME died: {why}", tell_me=False)
        if run_id is not None:
            lot = None
            with contextlib.suppress(DatabaseError):  # its lot then finds the machine Shutdown
                lot = _lot(self.transaction(Statement(_RUN_LOT, {"m": self.machine_id, "run": run_id})))
            await self._announce_run(run_id, AckCode.RUN_FAIL, "the ME died during the run", lot)

    async def _go_shutdown(self, note: str, tell_me: bool = True) -> None:
        """Machine to Shutdown: no operations accepted, status Shutdown, ME told (6.3.2.2)."""
        self.started = False
        await self.set_accept_types([])
        await self.change_status(S.SHUTDOWN, note=note)
        self.status = S.SHUTDOWN  # even if the Machine Server did not answer: we serve nothing now
        self.machine_run_id = self.recipe_id = None
        self.bus.set_interest(self.idle_interest())
        self.log.info("machine %s is Shutdown (%s)", self.machine_id, note)
        if tell_me:
            try:
                answer = await self.me_request(MeMessage(MessageId.ME_SHUT))
                if answer.message_id != MessageId.ME_SHUT_C or answer.ack_code != AckCode.ACK_OK:
                    self.log.warning("ME answered ME_SHUT with %s", answer.describe())
            except (MeDied, QueueError) as e:
                self.log.warning("ME did not acknowledge ME_SHUT: %s", e)

    async def alarm_action(self, msg: MeMessage) -> None:
        """An alarm from the ME: to the CAS, wait for the operator, then let the ME continue (ME_START_WAIT).

        An alarm raised while ME_START is out (the homing alarm) belongs to the start: a stop meanwhile
        withdraws it (cancel_start) and the ME is told REQ_CANCEL instead, so it stays shut down."""
        self._alarm_pending += 1
        try:
            alarm_id = msg.alarm_text or "UNKNOWN"
            self.log.info("the ME raises alarm %s", alarm_id)
            text = self._alarm_text(alarm_id)
            starting = self._starting is not None
            no = None
            if starting and self._start_cancelled is not None:  # the stop came first: not raised at all
                self.log.info("alarm %s not raised: the start it belongs to was cancelled", alarm_id)
            else:
                no = await self.raise_alarm(alarm_id, text, wait=False, retry=True)
            if no is not None:
                if starting:
                    self._start_alarms.add(no)
                    if self._start_cancelled is not None:  # the stop came while the CAS took the alarm
                        await self._withdraw_start_alarm(no)
                await self.wait_cleared(no)
            code = AckCode.ACK_OK if no is not None else AckCode.START_FAIL
            if starting and self._start_cancelled is not None:
                code = AckCode.REQ_CANCEL
            self.me.send(MeMessage(MessageId.ME_START_WAIT, alarm_text=alarm_id, seq=msg.seq, ack_code=code))
        except QueueError as e:
            self.log.error("could not tell the ME its alarm was cleared: %s", e)
        finally:
            self._alarm_pending -= 1
            self.me.heard = time.monotonic()

    # ----------------------------------------------------------------- a start cancelled by a stop

    async def _start_on_me(self) -> MeMessage:
        """ME_START to the ME: its answer comes once the machine is homed (its homing alarm cleared by
        the operator). StartCancelled when a stop came meanwhile (cancel_start), whatever the ME said:
        an ME that started all the same (the operator cleared the alarm as the stop came) is shut again."""
        if self._starting is not None:  # one ME_START at a time: a second would home the machine twice
            raise StartCancelled("another start is in progress (waiting for homing): this one is not sent")
        starting = self._starting = self._loop.create_future()
        self._start_cancelled, self._start_alarms = None, set()
        try:
            answer = await self.me_request(MeMessage(MessageId.ME_START))
        finally:
            starting.set_result(None)
            self._starting = None
        why = self._start_cancelled
        if why is None:
            return answer
        if answer.ack_code == AckCode.ACK_OK:
            self.log.warning("the ME started as the start was cancelled: ME_SHUT to the ME")
            try:
                await self.me_request(MeMessage(MessageId.ME_SHUT))
            except (MeDied, QueueError) as e:
                self.log.warning("ME did not acknowledge ME_SHUT: %s", e)
        raise StartCancelled(why)

    def cancel_start(self) -> Coroutine[Any, Any, str] | None:
        """A stop while ME_START is out (the machine waits to be homed): the start is cancelled."""
        if self._starting is None:
            return None
        return self._cancel_start(self._starting)

    async def _cancel_start(self, starting: asyncio.Future[None]) -> str:
        """The start's homing alarm withdrawn ("start cancelled"), the ME told REQ_CANCEL (alarm_action),
        and the start's end waited for: its ME_READY says it was cancelled; the machine stays Shutdown."""
        if self._start_cancelled is None:
            self._start_cancelled = START_CANCELLED
            self.log.warning("stop while ME_START waits for the machine to be homed: the start is cancelled")
            for no in list(self._start_alarms):
                await self._withdraw_start_alarm(no)
        try:
            async with asyncio.timeout(SERVER_TIMEOUT):
                await asyncio.shield(starting)
        except TimeoutError:
            self.log.warning("the ME has not answered the cancelled ME_START yet: the machine stays Shutdown")
        return START_CANCELLED

    async def _withdraw_start_alarm(self, alarm_no: int) -> None:
        """A cancelled start's alarm cleared by the WC itself, as "start cancelled": the operator's later
        clear finds it cleared, and nothing waits for it any more."""
        self._start_alarms.discard(alarm_no)
        try:
            answer = await self.ask(
                Conv.ALARM_CLR_REQ,
                message(Msg.ALARM_CLEAR_REQUEST, alarm_no=alarm_no, cleared_by=f"{self.name}: start cancelled"),
                "cas",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            self.log.error("Cell Alarm Server did not answer the clearing of alarm %d (start cancelled)", alarm_no)
        else:
            self.log.info("alarm %d withdrawn (start cancelled): %s %s", alarm_no, answer.ack_code, answer.note or "")
        self._done_waiting(alarm_no)

    # ----------------------------------------------------------------- a run's end

    def _results_path(self, run_id: int) -> Path:
        """Where the ME writes run `run_id`'s results: chosen by the WC, so a restarted WC finds them."""
        return self.results_dir / f"run-{run_id}.txt"

    def _outcome_in(self, path: Path) -> tuple[str, str | None]:
        """How the ME said the run of this results file ended (its RUN_COMPL's ack code and note)."""
        try:
            outcome = read_outcome(path)
        except (OSError, ValueError) as e:
            self.log.error("results file %s unreadable: %s", path, e)
            return AckCode.RUN_FAIL, f"results file unreadable: {e}"
        if outcome is None:
            return AckCode.ACK_OK, None
        try:
            return AckCode(outcome[0]), outcome[1] or None
        except ValueError:
            self.log.error("results file %s records an unknown outcome %r", path, outcome[0])
            return AckCode.RUN_FAIL, f"unknown outcome {outcome[0]} in the results file"

    def _stored_outcome(self, run_id: int) -> tuple[str, str | None] | None:
        """(ack code, note) of this run as stored with its results (MACHINE_RUN_OUTCOME); None if it was
        not stored (a read that fails counts as not)."""
        try:
            row = self._read(
                "SELECT ack_code, note FROM machine_run_outcome WHERE machine_run_id = %s AND machine_id = %s",
                (run_id, self.machine_id),
            )
        except DatabaseUnavailable:
            raise
        except DatabaseError as e:
            self.log.error("cannot read the stored outcome of run %d: %s", run_id, e)
            return None
        return None if row is None else (str(row[0]), row[1])

    async def run_complete(self, msg: MeMessage) -> None:
        """6.3.2.7: the ME's RUN_COMPL ends the run in progress.

        Also the run MACHINE_STATUS last named when the machine is Shutdown: its WC died mid-run and the
        Machine Server shut the machine down (liveness) before this WC started, while the ME finished
        the run. The part was made: its results are stored and announced, and the machine stays Shutdown.
        """
        async with self._state_lock:
            run_id = self.machine_run_id
            path = Path(msg.file_name) if msg.file_name else None
            code, note = msg.ack_code or AckCode.ACK_OK, msg.alarm_text or None
            if self.status in (S.RUNNING, S.RUN_SHUT) and run_id is not None:
                await self._finish_run(
                    run_id, code, path, note, "shutdown after run" if self.status == S.RUN_SHUT else None
                )
            elif (
                self.status == S.SHUTDOWN
                and run_id is not None
                and path == self._results_path(run_id)
                and path.exists()
            ):
                self.log.warning(
                    "run %d ended while its machine was Shutdown (its WC died mid-run): storing it", run_id
                )
                await self._finish_run(run_id, code, path, note, f"run {run_id} ended after its WC died", tell_me=False)
            else:
                self.log.warning(
                    "RUN_COMPL from the ME while %s: ignored (results file %s kept)",
                    self.status,
                    msg.file_name or "none",
                )

    async def _finish_run(
        self, run_id: int, code: str, path: Path | None, note: str | None, shutdown: str | None, tell_me: bool = True
    ) -> None:
        """Results into MACHINE_RUN_RESULT and the outcome into MACHINE_RUN_OUTCOME, file removed, Idle
        (Shutdown if `shutdown` says why), Run_Complete.

        Idempotent, so a restarted WC may complete a run its predecessor had begun to complete: the
        insert replaces rows already stored, and the file is removed only once they are stored.
        """
        results: dict[str, str] = {}
        if path is not None:
            try:
                results = read_results(path)
            except (OSError, ValueError) as e:
                self.log.error("results file %s unreadable: %s", path, e)
                code = AckCode.RUN_FAIL

        # The results and, with them, before Idle, the outcome: a lot that misses our Run_Complete (we die
        # before it goes out) finds the outcome here instead of running the operation again. One
        # statement, so one round trip, without BEGIN and COMMIT (db.Statement). It reads back whose run
        # it was: that lot is named to the bus as a listener of Run_Complete (a WC does not track lots).
        store = Statement(
            "WITH results AS (INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) "
            "    SELECT %(run)s, %(m)s, p, v FROM unnest(%(params)s::text[], %(values)s::text[]) AS r (p, v) "
            "    ON CONFLICT (machine_run_id, machine_id, param) DO UPDATE SET value = EXCLUDED.value) "
            "INSERT INTO machine_run_outcome (machine_run_id, machine_id, ack_code, note) "
            "VALUES (%(run)s, %(m)s, %(code)s, %(note)s) ON CONFLICT (machine_run_id, machine_id) DO UPDATE "
            "SET ack_code = EXCLUDED.ack_code, note = EXCLUDED.note, ended_at = clock_timestamp() "
            f"RETURNING ({_RUN_LOT})",
            {
                "run": run_id,
                "m": self.machine_id,
                "params": list(results),
                "values": list(results.values()),
                "code": str(code),
                "note": note,
            },
        )
        lot, stored = None, None
        try:
            # Results are kept (file and all) through a database outage rather than failing the run.
            lot = _lot(await self.transaction_when_up(store, within=DATABASE_OUTAGE_S))
        except DatabaseError as e:
            self.log.error("results of run %d not stored: %s (file %s kept)", run_id, e, path)
            code = AckCode.DB_BADUPD
        else:
            if sum(len(p) + len(v) for p, v in results.items()) <= INLINE_RESULTS:
                stored = results
            self.log.info("run %d: %d results stored in MACHINE_RUN_RESULT", run_id, len(results))
            if path is not None:
                path.unlink(missing_ok=True)
        if code != AckCode.ACK_OK:
            await self.raise_alarm(
                "RUN_FAIL", f"{self.machine_id}: run {run_id} failed ({code}{': ' + note if note else ''})", wait=False
            )
        self.machine_run_id = self.recipe_id = None
        await self._accepted_none(run_id)  # before the lot can give the machine back
        if shutdown is not None:
            await self._go_shutdown(shutdown, tell_me=tell_me)
            await self._announce_run(run_id, code, note, lot, stored)
            return
        # 6.3.2.7's order: Run_Complete, Idle, all operations (the machine is bound again only once MSCHED
        # has both). All operations once the Machine Server has the Idle: the lot's UNRESERVE, sent as it
        # hears the Run_Complete, then finds MSCHED free (docs/machine-interface.md 4.1).
        await self._announce_run(run_id, code, note, lot, stored)
        await self.change_status(S.IDLE, note=None if code == AckCode.ACK_OK else f"run {run_id}: {code}")
        await self.set_accept_types(ALL_OPERATIONS)

    async def _accepted_none(self, run_id: int) -> None:
        """The run's setup asked MSCHED for accepts-nothing without waiting: its answer, now."""
        accepting, self._accepting_none = self._accepting_none, None
        if accepting is None:
            return
        try:
            accepted = await accepting
        except GwcError as e:
            accepted = False
            self.log.error("run %d: accept types none: %s", run_id, e)
        if not accepted:
            self.log.error("run %d: MSCHED did not take its setup's accept types none", run_id)

    async def _announce_run(
        self, run_id: int, code: str, note: str | None, lot: str | None, results: dict[str, str] | None = None
    ) -> None:
        """Run_Complete; `results` as stored, when they are small enough to ride with it."""
        self.log.info("run %d complete (%s)%s", run_id, code, f": {note}" if note else "")
        conv = await self.bus.start(
            Conv.RUN_COMPL,
            message(
                Msg.RUN_COMPLETE,
                machine_id=self.machine_id,
                machine_run_id=run_id,
                ack_code=code,
                note=note,
                results=results,
            ),
            heard_by=(lot,) if lot else (),
        )
        conv.end()
