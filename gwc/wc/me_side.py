"""The WC's ME side (MeSide): the queue link to its ME, what the ME sends on its own (alarms, run
completions, the machine lost and back), starting the machine, a dead ME, the end of a run (results
stored, status, Run_Complete), and a restarted WC taking its machine up again (see gwc/wc/wc.py).

The machine lost while its ME runs: the CMM at the far end of its serial line hangs up, hangs, or
is power-cycled (gwc/me/cmm.py).

The ME says so (ME_LOST, with why) and goes on looking for the machine; the WC raises MACH_LOST with
the Cell Alarm Server, accepts no operation and has the Machine Server mark the machine Shutdown, so
MSCHED routes around it and a lot waiting for it is told. The WC stays started: the operator's
`gwc machine stop` still shuts it down for good (and the ME stops looking). When the ME hears the
machine again (ME_BACK) the WC clears its alarm, the machine is Idle and accepts its operations again.

The homing rule: the thesis homes the CMM when the operator starts its machine (ME_START raises
HOME_CMM, Listing 3). A machine coming back is not a start: no homing alarm is raised, so it comes
back by itself. A CMM whose controller lost power homes at its own power-on, before its Listing 9
program reads the line again; one that needs the operator is started again with `gwc machine stop`
and `gwc machine start`, which raise HOME_CMM as on any start. A stop while a start waits for its
HOME_CMM cancels that start: the WC withdraws the alarm ("start cancelled"), the ME stays shut down
(cancel_start).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

from gwc.cell import read_pid
from gwc.db import Statement
from gwc.errors import DatabaseError, DatabaseUnavailable, GwcError, QueueError
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.mq import Channel, MeMessage, MessageId
from gwc.ipc.names import Conv, Msg
from gwc.me import answer_deadline
from gwc.me.machine import MeState
from gwc.me.results import read_outcome, read_results
from gwc.module import DATABASE_OUTAGE_S, module_name
from gwc.wc.base import ALL_OPERATIONS, ME_DEADLINE, ME_PING, SERVER_TIMEOUT, MachineState, ServerCalls, WcHost
from gwc.wc.link import MeDied, MeLink

# A run's results ride in its Run_Complete when they are this small (characters of params and values
# together), so that its lot need not read them back; larger ones only in MACHINE_RUN_RESULT.
INLINE_RESULTS = 2000
# Whose run it is: the lot its Run_Complete must reach, named to the bus (a WC does not track lot scripts).
_RUN_LOT = "SELECT entity_id FROM reserved_machines WHERE machine_id = %(m)s AND machine_run_id = %(run)s"


def _lot(row: tuple[Any, ...] | None) -> str | None:
    return None if row is None or row[0] is None else f"lot:{row[0]}"


START_CANCELLED = "start cancelled: the machine was stopped before it was homed and started"


LOST_ALARM = "MACH_LOST"


class StartCancelled(GwcError):
    """ME_START was cancelled by a stop (ME_SHUT) while it waited for the machine to be homed."""


class MeSide:
    """Everything between the WC and its ME. The WC's handlers ask the ME through it (`ask_me`); what the
    ME sends on its own it handles itself, under the machine's state lock (MachineState.lock)."""

    def __init__(self, host: WcHost, state: MachineState, servers: ServerCalls) -> None:
        self.host = host
        self.state = state
        self.servers = servers
        cfg, log = host.cfg, host.log
        self.link = MeLink(Channel(cfg.ipc_prefix, state.machine_id, "wc", log), log, self._from_me)
        self.lost: str | None = None  # why the machine does not answer its ME, while it does not
        self.resuming = False  # a restarted WC checking its ME and its run: nothing served meanwhile
        self._lost_alarm: int | None = None  # the MACH_LOST alarm raised for it, cleared when it is back
        self._alarm_pending = 0  # alarms of ours waiting for the operator: ME answers may take that long
        self._starting: asyncio.Future[None] | None = None  # ME_START is out to the ME: done once it is answered
        self._start_cancelled: str | None = None  # why the ME_START out was cancelled (a stop came), once it was
        self._start_alarms: set[int] = set()  # the alarms (HOME_CMM) raised while that ME_START is out
        self._pidfd: int | None = None  # the ME's process, watched for its exit
        self._pidfd_loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        """Open the queue link (what the ME sent while no WC listened is read now) and watch the ME's
        process. QueueNotOurs: someone else's queue under our name, never used."""
        self.link.start(asyncio.get_running_loop())
        self.watch_process()

    def stop(self) -> None:
        """Stop watching the ME and close the link. Safe to call twice."""
        self.unwatch_process()
        self.link.stop()

    def _from_me(self, msg: MeMessage) -> None:
        """What the ME sends on its own: the machine lost or back, an alarm, or the end of a run."""
        if msg.message_id == MessageId.ME_LOST:
            self._spawn(self.machine_lost(msg.alarm_text or "no reason given"))
        elif msg.message_id == MessageId.ME_BACK:
            self._spawn(self.machine_back())
        elif msg.message_id == MessageId.CELL_ALAR:
            self._spawn(self.alarm_action(msg))
        else:
            self._spawn(self.run_complete(msg))

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Work the ME started, as a task of the WC's (cancelled when it stops), its failure logged."""
        self.host.spawn(self._guard(coro))

    async def _guard(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run work the ME started: log its failure, never lose it silently."""
        try:
            await coro
        except asyncio.CancelledError:
            raise
        except DatabaseUnavailable as e:
            self.host.log.error("work on a message from the ME failed: %s", e)
        except Exception:
            self.host.log.exception("work on a message from the ME failed")

    async def me_request(self, msg: MeMessage, timeout: float | None = None) -> MeMessage:
        """One request to the ME, waited for `timeout` or as long as this machine's ME may take
        (gwc.me.answer_deadline); the wait stays open while an alarm of ours waits for the operator."""
        wait = timeout if timeout is not None else answer_deadline(self.host.cfg.machine(self.state.machine_id))
        return await self.link.request(msg, wait, hold_open=lambda: self._alarm_pending > 0)

    async def ask_me(self, msg: MeMessage) -> tuple[MeMessage | None, tuple[str, str] | None]:
        """One request to the ME within a step: its answer, or the refusal the step gives (a dead ME
        is declared dead on the way)."""
        try:
            return await self.me_request(msg), None
        except MeDied as e:
            await self.me_died(str(e))
            return None, (AckCode.START_FAIL, f"ME failed: {e}")
        except QueueError as e:
            return None, (AckCode.START_FAIL, str(e))

    async def me_died(self, why: str) -> None:
        """6.3's ME is gone: alarm, a run in progress failed, machine Shutdown until the next ME_START.

        A run whose results file the ME wrote before it died (its RUN_COMPL read by a WC that died
        too) is completed from the file instead.
        """
        self.host.log.error("ME of %s is dead (%s): alarm, machine Shutdown", self.state.machine_id, why)
        run_id = (
            self.state.machine_run_id if self.state.status in (MachineStatus.RUNNING, MachineStatus.RUN_SHUT) else None
        )
        await self.servers.raise_alarm(
            "ME_DIED", f"machine side of {self.state.machine_id} stopped answering: {why}", wait=False
        )
        if run_id is not None and self.state.results_path(run_id).exists():
            path = self.state.results_path(run_id)
            self.host.log.warning(
                "run %d ended before the ME died: completing it from its results file %s", run_id, path
            )
            code, note = self._outcome_in(path)
            await self._finish_run(run_id, code, path, note, shutdown=f"ME died: {why}", tell_me=False)
            return
        await self.go_shutdown(f"ME died: {why}", tell_me=False)
        if run_id is not None:
            lot = None
            with contextlib.suppress(DatabaseError):  # its lot then finds the machine Shutdown
                lot = _lot(self.host.transaction(Statement(_RUN_LOT, {"m": self.state.machine_id, "run": run_id})))
            await self._announce_run(run_id, AckCode.RUN_FAIL, "the ME died during the run", lot)

    async def go_shutdown(self, note: str, tell_me: bool = True) -> None:
        """Machine to Shutdown: no operations accepted, status Shutdown, ME told (6.3.2.2). A machine shut
        down is not waited for any more (its MACH_LOST alarm stays for the operator)."""
        self.lost = None
        self.host.started = False
        await self.servers.set_accept_types([])
        await self.servers.change_status(MachineStatus.SHUTDOWN, note=note)
        self.state.status = MachineStatus.SHUTDOWN  # even if the Machine Server did not answer: we serve nothing now
        self.state.clear_run()
        self.host.bus.set_interest(self.host.idle_interest())
        self.host.log.info("machine %s is Shutdown (%s)", self.state.machine_id, note)
        if tell_me:
            try:
                answer = await self.me_request(MeMessage(MessageId.ME_SHUT))
                if answer.message_id != MessageId.ME_SHUT_C or answer.ack_code != AckCode.ACK_OK:
                    self.host.log.warning("ME answered ME_SHUT with %s", answer.describe())
            except (MeDied, QueueError) as e:
                self.host.log.warning("ME did not acknowledge ME_SHUT: %s", e)

    async def alarm_action(self, msg: MeMessage) -> None:
        """An alarm from the ME: to the CAS, wait for the operator, then let the ME continue (ME_START_WAIT).

        An alarm raised while ME_START is out (the homing alarm) belongs to the start: a stop meanwhile
        withdraws it (cancel_start) and the ME is told REQ_CANCEL instead, so it stays shut down."""
        self._alarm_pending += 1
        try:
            alarm_id = msg.alarm_text or "UNKNOWN"
            self.host.log.info("the ME raises alarm %s", alarm_id)
            text = self.servers.alarm_text(alarm_id)
            starting = self._starting is not None
            no = None
            if starting and self._start_cancelled is not None:  # the stop came first: not raised at all
                self.host.log.info("alarm %s not raised: the start it belongs to was cancelled", alarm_id)
            else:
                no = await self.servers.raise_alarm(alarm_id, text, wait=False, retry=True)
            if no is not None:
                if starting:
                    self._start_alarms.add(no)
                    if self._start_cancelled is not None:  # the stop came while the CAS took the alarm
                        await self._withdraw_start_alarm(no)
                await self.servers.wait_cleared(no)
            code = AckCode.ACK_OK if no is not None else AckCode.START_FAIL
            if starting and self._start_cancelled is not None:
                code = AckCode.REQ_CANCEL
            self.link.send(MeMessage(MessageId.ME_START_WAIT, alarm_text=alarm_id, seq=msg.seq, ack_code=code))
        except QueueError as e:
            self.host.log.error("could not tell the ME its alarm was cleared: %s", e)
        finally:
            self._alarm_pending -= 1
            self.link.heard = time.monotonic()

    # ----------------------------------------------------- starting the machine; a start cancelled by a stop

    async def start_machine(self) -> tuple[str, str | None]:
        if self.state.status != MachineStatus.SHUTDOWN:
            return AckCode.NOTNOW, f"the machine is {self.state.status}, not Shutdown"
        self.host.log.info("starting machine %s: ME_START to the ME", self.state.machine_id)
        try:
            answer = await self._start_on_me()
        except StartCancelled as e:
            return AckCode.REQ_CANCEL, str(e)
        except (MeDied, QueueError) as e:
            await self.servers.raise_alarm(
                "ME_DIED", f"machine side of {self.state.machine_id} did not answer ME_START: {e}", wait=False
            )
            return AckCode.START_FAIL, f"the ME did not start: {e}"
        if answer.ack_code != AckCode.ACK_OK:
            # Listing 3's MESTRT_FAIL ("See Error Log"), 3.2.2's alarm to turn the machine on: the operator
            # learns that the machine did not start, and why, where every alarm goes.
            why = f"{answer.ack_code} {answer.alarm_text or ''}".strip()
            await self.servers.raise_alarm(
                "MESTRT_FAIL", f"{self.state.machine_id} refused to start: {why}", wait=False
            )
            return AckCode.START_FAIL, f"the ME refused ME_START: {why}"
        if not await self.servers.change_status(MachineStatus.IDLE, expect=[MachineStatus.SHUTDOWN]):
            return AckCode.START_FAIL, "the Machine Server refused the change to Idle"
        if not await self.servers.set_accept_types(ALL_OPERATIONS):
            await self.servers.change_status(MachineStatus.SHUTDOWN, note="MSCHED did not take the accept types")
            return AckCode.START_FAIL, "MSCHED did not take the accept types"
        self.link.heard = time.monotonic()
        self.watch_process()  # a restarted ME has another process
        self.host.log.info("machine %s is Idle and accepts all its operations", self.state.machine_id)
        return AckCode.ACK_OK, None

    async def _start_on_me(self) -> MeMessage:
        """ME_START to the ME: its answer comes once the machine is homed (its homing alarm cleared by
        the operator). StartCancelled when a stop came meanwhile (cancel_start), whatever the ME said:
        an ME that started all the same (the operator cleared the alarm as the stop came) is shut again."""
        if self._starting is not None:  # one ME_START at a time: a second would home the machine twice
            raise StartCancelled("another start is in progress (waiting for homing): this one is not sent")
        starting = self._starting = asyncio.get_running_loop().create_future()
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
            self.host.log.warning("the ME started as the start was cancelled: ME_SHUT to the ME")
            try:
                await self.me_request(MeMessage(MessageId.ME_SHUT))
            except (MeDied, QueueError) as e:
                self.host.log.warning("ME did not acknowledge ME_SHUT: %s", e)
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
            self.host.log.warning("stop while ME_START waits for the machine to be homed: the start is cancelled")
            for no in list(self._start_alarms):
                await self._withdraw_start_alarm(no)
        try:
            async with asyncio.timeout(SERVER_TIMEOUT):
                await asyncio.shield(starting)
        except TimeoutError:
            self.host.log.warning("the ME has not answered the cancelled ME_START yet: the machine stays Shutdown")
        return START_CANCELLED

    async def _withdraw_start_alarm(self, alarm_no: int) -> None:
        """A cancelled start's alarm cleared by the WC itself, as "start cancelled": the operator's later
        clear finds it cleared, and nothing waits for it any more."""
        self._start_alarms.discard(alarm_no)
        answer = await self.servers.clear_alarm(alarm_no, f"{self.host.name}: start cancelled")
        if answer is None:
            self.host.log.error("Cell Alarm Server did not answer the clearing of alarm %d (start cancelled)", alarm_no)
        else:
            self.host.log.info(
                "alarm %d withdrawn (start cancelled): %s %s", alarm_no, answer.ack_code, answer.note or ""
            )
        self.servers.done_waiting(alarm_no)

    # ----------------------------------------------------------------- the machine lost and back (ME_LOST, ME_BACK)

    async def machine_lost(self, why: str) -> None:
        """The machine stopped answering its ME: alarm, no operations, Shutdown; the WC stays started.

        A run in progress was ended by the ME's RUN_COMPL (Run_Fail), sent before ME_LOST and completed
        first (the state lock is taken in turn). A machine already shut down (Run_Shut) is left so.
        """
        async with self.state.lock:
            if not self.host.started or self.lost is not None:
                self.host.log.warning(
                    "the ME lost the machine (%s) while it is %s: nothing to do", why, self.state.status
                )
                return
            self.lost = why
            self.host.log.error(
                "machine %s lost (%s): alarm, Shutdown until it answers again", self.state.machine_id, why
            )
            self._lost_alarm = (
                await self.servers.raise_alarm(LOST_ALARM, f"{self.state.machine_id}: {why}", wait=False) or None
            )
            if self.state.status == MachineStatus.SETUP_SHUT:  # the operator asked for a shutdown: it is one now
                await self.go_shutdown(f"machine lost: {why}")
                return
            await self.servers.set_accept_types([])
            if not await self.servers.change_status(MachineStatus.SHUTDOWN, note=f"machine lost: {why}"[:500]):
                self.state.status = MachineStatus.SHUTDOWN  # we serve nothing now, whatever the Machine Server says
            self.state.clear_run()

    async def machine_back(self) -> None:
        """The lost machine answers its ME again: alarm cleared, Idle, its operations accepted."""
        async with self.state.lock:
            if self.lost is None or not self.host.started:
                self.host.log.info(
                    "the ME hears its machine again; the machine is not waiting for it (%s)", self.state.status
                )
                return
            self.host.log.warning("machine %s answers again (it was lost: %s)", self.state.machine_id, self.lost)
            self.lost = None
            await self._clear_lost_alarm()
            if await self.servers.change_status(
                MachineStatus.IDLE, expect=[MachineStatus.SHUTDOWN], note=None
            ) and await self.servers.set_accept_types(ALL_OPERATIONS):
                self.host.log.info("machine %s is back: Idle, all operations accepted", self.state.machine_id)
                return
            await self.go_shutdown("the machine answers again but could not be brought back: start it again")

    async def _clear_lost_alarm(self) -> None:
        no, self._lost_alarm = self._lost_alarm, None
        if no is None:
            return
        answer = await self.servers.clear_alarm(no, self.host.name)
        if answer is None:
            self.host.log.error("Cell Alarm Server did not answer the clearing of alarm %d", no)
            return
        if answer.ack_code == AckCode.ACK_OK:
            self.host.log.info("alarm %d (%s) cleared: the machine answers again", no, LOST_ALARM)
        else:  # the operator cleared it already
            self.host.log.info(
                "alarm %d (%s) not cleared by us: %s %s", no, LOST_ALARM, answer.ack_code, answer.note or ""
            )

    # ----------------------------------------------------------------- a run's end

    def _outcome_in(self, path: Path) -> tuple[str, str | None]:
        """How the ME said the run of this results file ended (its RUN_COMPL's ack code and note)."""
        try:
            outcome = read_outcome(path)
        except (OSError, ValueError) as e:
            self.host.log.error("results file %s unreadable: %s", path, e)
            return AckCode.RUN_FAIL, f"results file unreadable: {e}"
        if outcome is None:
            return AckCode.ACK_OK, None
        try:
            return AckCode(outcome[0]), outcome[1] or None
        except ValueError:
            self.host.log.error("results file %s records an unknown outcome %r", path, outcome[0])
            return AckCode.RUN_FAIL, f"unknown outcome {outcome[0]} in the results file"

    def _stored_outcome(self, run_id: int) -> tuple[str, str | None] | None:
        """(ack code, note) of this run as stored with its results (MACHINE_RUN_OUTCOME); None if it was
        not stored (a read that fails counts as not)."""
        try:
            row = self.servers.read(
                "SELECT ack_code, note FROM machine_run_outcome WHERE machine_run_id = %s AND machine_id = %s",
                (run_id, self.state.machine_id),
            )
        except DatabaseUnavailable:
            raise
        except DatabaseError as e:
            self.host.log.error("cannot read the stored outcome of run %d: %s", run_id, e)
            return None
        return None if row is None else (str(row[0]), row[1])

    async def run_complete(self, msg: MeMessage) -> None:
        """6.3.2.7: the ME's RUN_COMPL ends the run in progress.

        Also the run MACHINE_STATUS last named when the machine is Shutdown: its WC died mid-run and the
        Machine Server shut the machine down (liveness) before this WC started, while the ME finished
        the run. The part was made: its results are stored and announced, and the machine stays Shutdown.
        """
        async with self.state.lock:
            run_id = self.state.machine_run_id
            path = Path(msg.file_name) if msg.file_name else None
            code, note = msg.ack_code or AckCode.ACK_OK, msg.alarm_text or None
            if self.state.status in (MachineStatus.RUNNING, MachineStatus.RUN_SHUT) and run_id is not None:
                await self._finish_run(
                    run_id,
                    code,
                    path,
                    note,
                    "shutdown after run" if self.state.status == MachineStatus.RUN_SHUT else None,
                )
            elif (
                self.state.status == MachineStatus.SHUTDOWN
                and run_id is not None
                and path == self.state.results_path(run_id)
                and path.exists()
            ):
                self.host.log.warning(
                    "run %d ended while its machine was Shutdown (its WC died mid-run): storing it", run_id
                )
                await self._finish_run(run_id, code, path, note, f"run {run_id} ended after its WC died", tell_me=False)
            else:
                self.host.log.warning(
                    "RUN_COMPL from the ME while %s: ignored (results file %s kept)",
                    self.state.status,
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
                self.host.log.error("results file %s unreadable: %s", path, e)
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
                "m": self.state.machine_id,
                "params": list(results),
                "values": list(results.values()),
                "code": str(code),
                "note": note,
            },
        )
        lot, stored = None, None
        try:
            # Results are kept (file and all) through a database outage rather than failing the run.
            lot = _lot(await self.host.transaction_when_up(store, within=DATABASE_OUTAGE_S))
        except DatabaseError as e:
            self.host.log.error("results of run %d not stored: %s (file %s kept)", run_id, e, path)
            code = AckCode.DB_BADUPD
        else:
            if sum(len(p) + len(v) for p, v in results.items()) <= INLINE_RESULTS:
                stored = results
            self.host.log.info("run %d: %d results stored in MACHINE_RUN_RESULT", run_id, len(results))
            if path is not None:
                path.unlink(missing_ok=True)
        if code != AckCode.ACK_OK:
            await self.servers.raise_alarm(
                "RUN_FAIL",
                f"{self.state.machine_id}: run {run_id} failed ({code}{': ' + note if note else ''})",
                wait=False,
            )
        self.state.clear_run()
        await self.servers.accepted_none(run_id)  # before the lot can give the machine back
        if shutdown is not None:
            await self.go_shutdown(shutdown, tell_me=tell_me)
            await self._announce_run(run_id, code, note, lot, stored)
            return
        # 6.3.2.7's order: Run_Complete, Idle, all operations (the machine is bound again only once MSCHED
        # has both). All operations once the Machine Server has the Idle: the lot's UNRESERVE, sent as it
        # hears the Run_Complete, then finds MSCHED free (docs/machine-interface.md 4.1).
        await self._announce_run(run_id, code, note, lot, stored)
        await self.servers.change_status(
            MachineStatus.IDLE, note=None if code == AckCode.ACK_OK else f"run {run_id}: {code}"
        )
        await self.servers.set_accept_types(ALL_OPERATIONS)

    async def _announce_run(
        self, run_id: int, code: str, note: str | None, lot: str | None, results: dict[str, str] | None = None
    ) -> None:
        """Run_Complete; `results` as stored, when they are small enough to ride with it."""
        self.host.log.info("run %d complete (%s)%s", run_id, code, f": {note}" if note else "")
        conv = await self.host.bus.start(
            Conv.RUN_COMPL,
            message(
                Msg.RUN_COMPLETE,
                machine_id=self.state.machine_id,
                machine_run_id=run_id,
                ack_code=code,
                note=note,
                results=results,
            ),
            heard_by=(lot,) if lot else (),
        )
        conv.end()

    # ----------------------------------------------------------------- watching the ME; a restarted WC resuming

    @property
    def me_up(self) -> bool:
        """The ME should be up and is watched: the machine is, or it is lost (its ME looks for it)."""
        return self.state.status != MachineStatus.SHUTDOWN or self.lost is not None

    async def ping_if_quiet(self) -> None:
        """Watch the ME: ping it when quiet; declare it dead when a ping goes unanswered."""
        if self.resuming or not self.me_up or self.link.busy or time.monotonic() - self.link.heard < ME_PING:
            return
        try:
            answer = await self.me_request(MeMessage(MessageId.NO_MESSAGE), timeout=ME_DEADLINE)
        except (MeDied, QueueError) as e:
            if self.me_up:
                await self.me_died(str(e))
            return
        if answer.ack_code != AckCode.ACK_OK and self.me_up:
            await self.me_died(
                f"the ME answers that it is shut down ({answer.alarm_text or answer.ack_code}): "
                "it was restarted and lost the machine's state"
            )

    def watch_process(self) -> None:
        """Watch the ME's process by its pid file (written by whoever started it): the kernel tells its
        exit at once (a pidfd), and the next heartbeat pings the ME to confirm, so the idle pings
        (ME_PING) are left to find an ME that hangs. No pid file: the pings alone, as before."""
        self.unwatch_process()
        name = module_name("me", self.state.machine_id)
        st = read_pid(self.host.cfg, name)
        if not st.alive or st.pid is None:
            return
        try:
            fd = os.pidfd_open(st.pid)
        except OSError:
            return
        if read_pid(self.host.cfg, name).pid != st.pid:  # the pid file changed meanwhile: not that process
            os.close(fd)
            return
        self._pidfd = fd
        self._pidfd_loop = asyncio.get_running_loop()
        self._pidfd_loop.add_reader(fd, self._me_process_exited, st.pid)

    def unwatch_process(self) -> None:
        fd, self._pidfd = self._pidfd, None
        if fd is not None:
            if self._pidfd_loop is not None and not self._pidfd_loop.is_closed():
                self._pidfd_loop.remove_reader(fd)
            os.close(fd)

    def _me_process_exited(self, pid: int) -> None:
        self.unwatch_process()
        self.host.log.warning("the ME's process (pid %d) exited: pinging it at the next heartbeat", pid)
        self.link.heard = -math.inf

    def resume_soon(self) -> None:
        """A WC restarted while its machine was up: take it up again (resume) in the background."""
        self.resuming = True
        self._spawn(self._resume())

    async def _resume(self) -> None:
        """A WC restarted while its machine was up: check the ME, then the run, then serve again.

        Until this is done the WC is not started, so what the cell asks meanwhile (SETUP_RUN from a
        scheduler that still sees the machine Idle) is answered Notnow, never passed to an ME that
        cannot serve it.
        """
        try:
            answer: MeMessage | None
            try:
                answer = await self.me_request(MeMessage(MessageId.NO_MESSAGE), timeout=ME_DEADLINE)
            except (MeDied, QueueError) as e:
                answer, why = None, f"no ME answers: {e}"
            else:
                why = (
                    f"the ME answers that it is shut down ({answer.alarm_text or answer.ack_code}): it was "
                    "restarted and lost the machine's state"
                )
            async with self.state.lock:
                if answer is None or answer.ack_code != AckCode.ACK_OK:
                    if self.state.status != MachineStatus.SHUTDOWN:  # (a RUN_COMPL that waited may have shut it down)
                        await self.me_died(why)
                    return
                await self._reconcile_run(answer)
                self.host.started = self.state.status in (
                    MachineStatus.IDLE,
                    MachineStatus.SETUP,
                    MachineStatus.RUNNING,
                )
                self.host.bus.set_interest(
                    self.host.busy_interest() if self.host.started else self.host.idle_interest()
                )
                self.host.log.info(
                    "machine %s resumed: %s, the ME is %s",
                    self.state.machine_id,
                    self.state.status,
                    answer.alarm_text or "up",
                )
        finally:
            self.resuming = False
            self.link.heard = time.monotonic()

    async def _reconcile_run(self, me: MeMessage) -> None:
        """The run MACHINE_STATUS says is running, as it really is (the ME is up and answered `me`).

        Its results file exists: the run ended and its RUN_COMPL was read by the WC that died (or
        never handled): complete it from the file. The ME runs it: its RUN_COMPL will come. Neither,
        but the dead WC stored the run (MACHINE_RUN_OUTCOME): announce it as stored. Else the results
        are lost: complete it without them, so the lot hears and the machine is Idle again.
        """
        run_id = self.state.machine_run_id
        if self.state.status not in (MachineStatus.RUNNING, MachineStatus.RUN_SHUT) or run_id is None:
            return
        path = self.state.results_path(run_id)
        shutdown = "shutdown after run" if self.state.status == MachineStatus.RUN_SHUT else None
        if path.exists():
            code, note = self._outcome_in(path)
            self.host.log.warning(
                "run %d ended while no WC handled it: completing it from its results file %s", run_id, path
            )
            await self._finish_run(run_id, code, path, note, shutdown)
        elif me.alarm_text == MeState.RUNNING and me.file_name == str(path):
            self.host.log.info("run %d is still in progress on the ME", run_id)
        elif (stored := self._stored_outcome(run_id)) is not None:
            self.host.log.warning(
                "run %d: stored (%s) before the WC died, not announced: completing it", run_id, stored[0]
            )
            await self._finish_run(run_id, stored[0], None, stored[1], shutdown)
        else:
            self.host.log.error(
                "run %d: no results file and the ME is %s with no run: the results are lost",
                run_id,
                me.alarm_text or "up",
            )
            await self._finish_run(
                run_id, AckCode.RUN_FAIL, None, "results lost: the run ended while its WC was down", shutdown
            )
