"""WC, the cell side of a machine interface (thesis 6.3): one program for every machine.

The WC is the machine's voice on the bus. It serves ME_START, ME_SHUT, SETUP_RUN, START_RUN,
DNLD_ME and UPLD_ME, and carries what its ME reports (alarms, run completions) to the cell. It talks
to its ME over the machine's queue pair (gwc.ipc.mq), one request at a time, each answered by an
ack carrying the request's sequence number. It never writes another module's tables: status changes
go to the Machine Server (CHG_STATUS), accept types to MSCHED (ACC_TYP_C), alarms to the Cell Alarm
Server (ALARM_SEND), recipes come from the Equipment Recipe Server (RECIPE_GET). It writes only
MACHINE_RUN_RESULT rows of its own runs.

The steps that move the machine from one status to another (setup, start, run completion,
shutdown) take turns on one lock, so a run that completes before its START_RUN has been recorded,
or a shutdown that arrives in the middle of a setup, waits for the step in progress and then finds
the status that step left.

Its ME is watched: the WC pings it (NO_MESSAGE) when it has heard nothing for `ME_PING` seconds;
an ME that does not answer within `ME_DEADLINE`, or answers that it is shut down while the machine
is up (it was restarted and lost its state), is dead: alarm ME_DIED, a run in progress ends with
Run_Complete(Run_Fail), the machine goes Shutdown, and the WC waits for the operator's next
ME_START (6.3.2.1) once the ME has been restarted.

A WC restarted (kill -9) while MACHINE_STATUS says its machine is up serves nothing (Notnow) until it
has checked, first, that its ME is still the started ME (a fresh ME, or none, means the machine is
down: Shutdown until ME_START) and, second, what became of the run the status names: the results
file of run N (the WC chose its path, results_dir/run-N.txt) outlives a RUN_COMPL the dead WC read
and never handled, and the ME says whether it is still running it (see _resume).
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import time
from collections.abc import Awaitable, Callable, Coroutine
from pathlib import Path
from typing import Any

import psycopg

from gwc.config import Config
from gwc.errors import ConversationTimeout, DatabaseError, DatabaseUnavailable, QueueError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.mq import Channel, MeMessage, MessageId
from gwc.me.machine import MeState
from gwc.me.results import read_outcome, read_results
from gwc.module import Handler, Module
from gwc.wc.link import MeDied, MeLink

ME_PING = 0.5  # ping the ME after this long without hearing from it
ME_DEADLINE = 1.5  # an ME silent this long after a ping is dead
ME_ANSWER = 10.0  # longest an ME may take to acknowledge a request (not counting operator alarms)
SERVER_TIMEOUT = 5.0  # longest a server may take to answer the WC
SERVER_RESTART = 30.0  # how long the WC asks a restarting server again (status, accept types)
ABANDONED_S = 10.0  # a setup whose run has not been reserved this long is given up (its lot is gone)
SETUP_CHECK_S = 2.0  # how often a machine in Setup looks for its run's reservation
ALL_OPERATIONS = ["*"]
S = MachineStatus


class WC(Module):
    role = "wc"
    start_class = "ME_START"
    stop_class = "ME_SHUT"
    always = ("ALARM_CLE",)

    def __init__(self, cfg: Config, name: str, log: logging.Logger, machine_id: str) -> None:
        # Before the base's __init__: it asks idle_interest(), which depends on the status.
        self.status = S.SHUTDOWN  # our copy of MACHINE_STATUS.status; the Machine Server holds the truth
        super().__init__(cfg, name, log)
        self.machine_id = machine_id
        self.machine_run_id: int | None = None
        self.recipe_id: str | None = None
        self.me = MeLink(Channel(cfg.ipc_prefix, machine_id, "wc", log), log, self._from_me)
        self.recipe_dir = cfg.var / "recipes" / machine_id
        self.results_dir = cfg.results_dir / machine_id
        self._state_lock = asyncio.Lock()  # one status-changing step at a time
        self._alarm_waits: dict[int, asyncio.Future[None]] = {}
        self._cleared: set[int] = set()  # alarm numbers seen cleared (a clear may beat our wait for it)
        self._alarm_pending = 0  # alarms of ours waiting for the operator: ME answers may take that long
        self._start_note: str | None = None  # why the last ME_START failed, for ME_Ready's note
        self._resuming = False  # a restarted WC checking its ME and its run: nothing served meanwhile
        self._setup_checked = 0.0  # when the run set up was last found reserved (or not) ...
        self._unreserved_since: float | None = None  # ... and since when it is not

    # ----------------------------------------------------------------- module hooks

    def handlers(self) -> dict[str, Handler]:
        return {
            "SETUP_RUN": self.setup_run,
            "START_RUN": self.start_run,
            "DNLD_ME": self.download,
            "UPLD_ME": self.upload,
            "ALARM_CLE": self.alarm_cleared,
        }

    def serves(self, cls: str) -> bool:
        # A machine set up before a shutdown request may still start its run (Setup_Shut, 6.3.2.4).
        return super().serves(cls) or (cls == "START_RUN" and self.status == S.SETUP_SHUT)

    def idle_interest(self) -> set[str]:
        extra = {"START_RUN"} if self.status == S.SETUP_SHUT else set()
        return super().idle_interest() | extra

    def startup_complete(self, code: str) -> Message:
        return message("ME_Ready", machine_id=self.machine_id, ack_code=code, note=self._start_note)

    def shutdown_complete(self, note: str | None) -> Message:
        return message("ME_Stopped", machine_id=self.machine_id, ack_code=AckCode.ACK_OK, note=note)

    async def run(self, start: bool = False) -> int:
        try:
            return await super().run(start)
        finally:
            self.me.stop()

    async def on_bus(self) -> None:
        self.status, self.machine_run_id, self.recipe_id = self._read_status()
        # What the ME sent while no WC listened is read now (a RUN_COMPL is completed by its own task,
        # which takes the state lock before _resume looks at the run).
        self.me.start(self._loop)
        if self.status != S.SHUTDOWN:
            self.log.warning(
                "machine %s is %s (run %s): resuming it", self.machine_id, self.status, self.machine_run_id
            )
            self._resuming = True
            self._spawn(self._resume())

    async def _resume(self) -> None:
        """A WC restarted while its machine was up: check the ME, then the run, then serve again.

        Until this is done the WC is not started, so what the cell asks meanwhile (SETUP_RUN from a
        scheduler that still sees the machine Idle) is answered Notnow, never passed to an ME that
        cannot serve it.
        """
        try:
            try:
                answer: MeMessage | None = await self.me_request(MeMessage(MessageId.NO_MESSAGE), timeout=ME_DEADLINE)
            except (MeDied, QueueError) as e:
                answer, why = None, f"no ME answers: {e}"
            else:
                why = (
                    f"the ME answers that it is shut down ({answer.alarm_text or answer.ack_code}): it was "
                    "restarted and lost the machine's state"
                )
            async with self._state_lock:
                if answer is None or answer.ack_code != AckCode.ACK_OK:
                    if self.status != S.SHUTDOWN:  # (a RUN_COMPL that waited may have shut it down)
                        await self.me_died(why)
                    return
                await self._reconcile_run(answer)
                self.started = self.status in (S.IDLE, S.SETUP, S.RUNNING)
                self.bus.set_interest(self.busy_interest() if self.started else self.idle_interest())
                self.log.info(
                    "machine %s resumed: %s, the ME is %s", self.machine_id, self.status, answer.alarm_text or "up"
                )
        finally:
            self._resuming = False
            self.me.heard = time.monotonic()

    async def _reconcile_run(self, me: MeMessage) -> None:
        """The run MACHINE_STATUS says is running, as it really is (the ME is up and answered `me`).

        Its results file exists: the run ended and its RUN_COMPL was read by the WC that died (or
        never handled): complete it from the file. The ME runs it: its RUN_COMPL will come. Neither,
        but the dead WC stored the run (MACHINE_RUN_OUTCOME): announce it as stored. Else the results
        are lost: complete it without them, so the lot hears and the machine is Idle again.
        """
        run_id = self.machine_run_id
        if self.status not in (S.RUNNING, S.RUN_SHUT) or run_id is None:
            return
        path = self._results_path(run_id)
        shutdown = "shutdown after run" if self.status == S.RUN_SHUT else None
        if path.exists():
            code, note = self._outcome_in(path)
            self.log.warning(
                "run %d ended while no WC handled it: completing it from its results file %s", run_id, path
            )
            await self._finish_run(run_id, code, path, note, shutdown)
        elif me.alarm_text == MeState.RUNNING and me.file_name == str(path):
            self.log.info("run %d is still in progress on the ME", run_id)
        elif (stored := self._stored_outcome(run_id)) is not None:
            self.log.warning("run %d: stored (%s) before the WC died, not announced: completing it", run_id, stored[0])
            await self._finish_run(run_id, stored[0], None, stored[1], shutdown)
        else:
            self.log.error(
                "run %d: no results file and the ME is %s with no run: the results are lost",
                run_id,
                me.alarm_text or "up",
            )
            await self._finish_run(
                run_id, AckCode.RUN_FAIL, None, "results lost: the run ended while its WC was down", shutdown
            )

    async def on_startup(self) -> str:
        """6.3.2.1: ME_START to the ME (homing alarm passed on and cleared), Idle, all operations."""
        code, self._start_note = await self._startup_machine()
        if code != AckCode.ACK_OK:
            self.log.error("machine %s not started: %s (%s)", self.machine_id, code, self._start_note)
        return code

    async def _startup_machine(self) -> tuple[str, str | None]:
        if self.status != S.SHUTDOWN:
            return AckCode.NOTNOW, f"the machine is {self.status}, not Shutdown"
        self.log.info("starting machine %s: ME_START to the ME", self.machine_id)
        try:
            answer = await self.me_request(MeMessage(MessageId.ME_START))
        except (MeDied, QueueError) as e:
            await self.raise_alarm(
                "ME_DIED", f"machine side of {self.machine_id} did not answer ME_START: {e}", wait=False
            )
            return AckCode.START_FAIL, f"the ME did not start: {e}"
        if answer.ack_code != AckCode.ACK_OK:
            return AckCode.START_FAIL, f"the ME refused ME_START: {answer.ack_code} {answer.alarm_text}"
        if not await self.change_status(S.IDLE, expect=[S.SHUTDOWN]):
            return AckCode.START_FAIL, "the Machine Server refused the change to Idle"
        if not await self.set_accept_types(ALL_OPERATIONS):
            await self.change_status(S.SHUTDOWN, note="MSCHED did not take the accept types")
            return AckCode.START_FAIL, "MSCHED did not take the accept types"
        self.me.heard = time.monotonic()
        self.log.info("machine %s is Idle and accepts all its operations", self.machine_id)
        return AckCode.ACK_OK, None

    async def on_shutdown(self) -> str | None:
        """6.3.2.2: Idle shuts down at once; Setup and Running shut down when their run is over."""
        async with self._state_lock:
            await self.set_accept_types([])
            if self.status == S.SETUP:
                await self.change_status(S.SETUP_SHUT, expect=[S.SETUP])
                self.bus.set_interest(self.idle_interest())
                self.log.info("shutdown pending: the machine is set up; it shuts down after its run")
                return "shutdown pending: the machine is set up; it shuts down after its run"
            if self.status == S.RUNNING:
                await self.change_status(S.RUN_SHUT, expect=[S.RUNNING])
                self.log.info("shutdown pending: the machine shuts down when its run completes")
                return "shutdown pending: the machine shuts down when its run completes"
            if self.status in (S.SETUP_SHUT, S.RUN_SHUT):
                return "shutdown already pending"
            await self._go_shutdown("operator shutdown")
            return None

    async def on_idle(self) -> None:
        """Give up an abandoned setup; watch the ME: ping it when quiet; declare it dead when a ping goes
        unanswered."""
        await self._give_up_abandoned_setup()
        if self._resuming or self.status == S.SHUTDOWN or self.me.busy or time.monotonic() - self.me.heard < ME_PING:
            return
        try:
            answer = await self.me_request(MeMessage(MessageId.NO_MESSAGE), timeout=ME_DEADLINE)
        except (MeDied, QueueError) as e:
            if self.status != S.SHUTDOWN:
                await self.me_died(str(e))
            return
        if answer.ack_code != AckCode.ACK_OK and self.status != S.SHUTDOWN:
            await self.me_died(
                f"the ME answers that it is shut down ({answer.alarm_text or answer.ack_code}): "
                "it was restarted and lost the machine's state"
            )

    async def _give_up_abandoned_setup(self) -> None:
        """A machine set up for a run that MSCHED no longer reserves for it goes Idle again.

        The lot that set it up gave up or died between SETUP_RUN and START_RUN, and was unreserved.
        Nobody will start that run, and the machine serves SETUP_RUN only when Idle: without this it
        would stay in Setup for good. The run must be missing from RESERVED_MACHINES for ABANDONED_S
        first, so a reservation is never raced.
        """
        run_id, now = self.machine_run_id, time.monotonic()
        if self.status not in (S.SETUP, S.SETUP_SHUT) or run_id is None:
            self._unreserved_since = None
            return
        if now - self._setup_checked < SETUP_CHECK_S:
            return
        self._setup_checked = now
        try:
            reserved = (
                self._read(
                    "SELECT 1 FROM reserved_machines WHERE machine_id = %s AND machine_run_id = %s",
                    (self.machine_id, run_id),
                )
                is not None
            )
        except DatabaseUnavailable:
            raise
        except DatabaseError as e:
            self.log.warning("cannot check the reservation of run %d: %s", run_id, e)
            return
        if reserved or self._unreserved_since is None:
            self._unreserved_since = None if reserved else now
            return
        if now - self._unreserved_since < ABANDONED_S:
            return
        async with self._state_lock:
            if self.status not in (S.SETUP, S.SETUP_SHUT) or self.machine_run_id != run_id:
                return
            self.log.warning(
                "run %d is set up but not reserved any more (its lot gave up or died): giving it up", run_id
            )
            self.machine_run_id = self.recipe_id = None
            self._unreserved_since = None
            if self.status == S.SETUP_SHUT:
                await self._go_shutdown(f"shutdown after run {run_id} was given up")
            else:
                await self.change_status(S.IDLE, expect=[S.SETUP], note=f"run {run_id} given up: not reserved")
                await self.set_accept_types(ALL_OPERATIONS)

    # ----------------------------------------------------------------- the ME side

    @property
    def _loop(self) -> asyncio.AbstractEventLoop:
        loop = self.bus._loop
        assert loop is not None
        return loop

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
            self._fatal(e)
        except Exception:
            self.log.exception("work on a message from the ME failed")

    async def me_request(self, msg: MeMessage, timeout: float = ME_ANSWER) -> MeMessage:
        """One request to the ME; the wait stays open while an alarm of ours waits for the operator."""
        return await self.me.request(msg, timeout, hold_open=lambda: self._alarm_pending > 0)

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
            await self._finish_run(run_id, *self._outcome_in(path), shutdown=f"ME died: {why}", tell_me=False)
            return
        await self._go_shutdown(f"ME died: {why}", tell_me=False)
        if run_id is not None:
            await self._announce_run(run_id, AckCode.RUN_FAIL, "the ME died during the run")

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

    # ----------------------------------------------------------------- asking the servers

    def _read_status(self) -> tuple[MachineStatus, int | None, str | None]:
        row = self._read(
            "SELECT status, machine_run_id, recipe_id FROM machine_status WHERE machine_id = %s", (self.machine_id,)
        )
        return (MachineStatus(row[0]), row[1], row[2]) if row else (S.SHUTDOWN, None, None)

    def _read(self, sql: str, params: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """One row read; DatabaseError (answered DB_Badrea by the callers) if the database fails."""
        try:
            conn = self.db()
            row = conn.execute(sql, params).fetchone()
            conn.rollback()
            return row
        except psycopg.Error as e:
            if self._conn is not None and (self._conn.broken or self._conn.closed):
                self._conn.close()
            raise DatabaseError(f"database read failed: {' '.join(str(e).split())}") from e

    async def change_status(
        self, status: MachineStatus, expect: list[MachineStatus] | None = None, **fields: Any
    ) -> bool:
        """Ask the Machine Server to change our status; keep our copy in step when it agrees."""
        try:
            answer = await self.ask(
                "CHG_STATUS",
                message(
                    "Change_Status",
                    machine_id=self.machine_id,
                    status=status,
                    expect=[str(s) for s in expect] if expect else None,
                    **fields,
                ),
                "ms",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            self.log.error("Machine Server did not answer the change to %s", status)
            return False
        # A refusal that names the status asked for is no refusal: asked again after the Machine
        # Server restarted, the first change had been made.
        if answer.ack_code != AckCode.ACK_OK and answer.status != status:
            self.log.error("Machine Server refused %s: %s %s", status, answer.ack_code, answer.note or "")
            if answer.status:
                self.status = MachineStatus(answer.status)
            return False
        self.log.info("status %s -> %s", self.status, status)
        self.status = status
        return True

    async def set_accept_types(self, op_types: list[str]) -> bool:
        try:
            answer = await self.ask(
                "ACC_TYP_C",
                message("Chg_Accept_Type", machine_id=self.machine_id, op_types=op_types),
                "msched",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            self.log.error("MSCHED did not answer the accept-type change to %s", op_types or "none")
            return False
        if answer.ack_code != AckCode.ACK_OK:
            self.log.error("MSCHED refused accept types %s: %s", op_types, answer.ack_code)
            return False
        self.log.info("accept types: %s", "all operations" if op_types == ALL_OPERATIONS else op_types or "none")
        return True

    async def raise_alarm(self, alarm_id: str, text: str, wait: bool) -> bool:
        """6.3.2.8: pass an alarm to the CAS; when `wait`, hold until the operator clears it."""
        while True:
            try:
                answer = await self.ask(
                    "ALARM_SEND",
                    message(
                        "Alarm_Send",
                        alarm_id=alarm_id,
                        alarm_text=text,
                        machine_id=self.machine_id,
                        raised_by=self.name,
                    ),
                    "cas",
                    SERVER_TIMEOUT,
                )
                break
            except ConversationTimeout:
                if not wait:
                    self.log.error("Cell Alarm Server did not take alarm %s", alarm_id)
                    return False
                self.log.error("Cell Alarm Server did not take alarm %s: trying again", alarm_id)
        if answer.ack_code != AckCode.ACK_OK or answer.alarm_no is None:
            self.log.error("Cell Alarm Server refused alarm %s: %s", alarm_id, answer.ack_code)
            return False
        self.log.info("alarm %d (%s) raised: %s", answer.alarm_no, alarm_id, text)
        if not wait:
            return True
        if answer.alarm_no in self._cleared:
            return True
        cleared = self._loop.create_future()
        self._alarm_waits[answer.alarm_no] = cleared
        self.log.info("alarm %d (%s) pending: waiting for the operator to clear it", answer.alarm_no, alarm_id)
        try:
            await cleared
        finally:
            self._alarm_waits.pop(answer.alarm_no, None)
        self.log.info("alarm %d cleared: continuing", answer.alarm_no)
        return True

    async def alarm_cleared(self, conv: Conversation) -> None:
        assert conv.first is not None
        clear = conv.first.first
        if clear.machine_id not in (None, self.machine_id):
            return
        self._cleared.add(clear.alarm_no)
        waiter = self._alarm_waits.get(clear.alarm_no)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def alarm_action(self, msg: MeMessage) -> None:
        """An alarm from the ME: to the CAS, wait for the operator, then let the ME continue (ME_START_WAIT)."""
        self._alarm_pending += 1
        try:
            alarm_id = msg.alarm_text or "UNKNOWN"
            self.log.info("the ME raises alarm %s", alarm_id)
            text = self._alarm_text(alarm_id)
            cleared = await self.raise_alarm(alarm_id, text, wait=True)
            self.me.send(
                MeMessage(
                    MessageId.ME_START_WAIT,
                    alarm_text=alarm_id,
                    seq=msg.seq,
                    ack_code=AckCode.ACK_OK if cleared else AckCode.START_FAIL,
                )
            )
        except QueueError as e:
            self.log.error("could not tell the ME its alarm was cleared: %s", e)
        finally:
            self._alarm_pending -= 1
            self.me.heard = time.monotonic()

    def _alarm_text(self, alarm_id: str) -> str:
        try:
            row = self._read("SELECT alarm_text FROM alarm_description WHERE alarm_id = %s", (alarm_id,))
        except DatabaseError as e:
            self.log.error("cannot check alarm %s in ALARM_DESCRIPTION: %s", alarm_id, e)
            row = None
        if row is None:
            self.log.warning("alarm %s is not in ALARM_DESCRIPTION: passing it on as unknown", alarm_id)
            return f"unknown alarm {alarm_id} from {self.machine_id}"
        return f"{self.machine_id}: {row[0]}"

    # ----------------------------------------------------------------- the conversations served

    async def _refuse_now(self, conv: Conversation, ack: str, code: str, note: str) -> None:
        self.log.info("refused %s: %s (%s)", conv.cls, code, note)
        await conv.send(message(ack, ack_code=code, note=note[:500]))

    def _check(self, req: Message, allowed: tuple[MachineStatus, ...]) -> tuple[str, str] | None:
        """Why this request cannot be served now, as (ack code, note); None if it can."""
        if req.machine_id != self.machine_id:
            return AckCode.BAD_MESSAGE, f"this is the WC of {self.machine_id}, not of {req.machine_id}"
        if self.status not in allowed:
            return AckCode.NOTNOW, f"machine is {self.status}, not {' or '.join(allowed)}"
        return None

    async def _ask_me(self, msg: MeMessage) -> tuple[MeMessage | None, tuple[str, str] | None]:
        """One request to the ME within a step: its answer, or the refusal the step gives (a dead ME
        is declared dead on the way)."""
        try:
            return await self.me_request(msg), None
        except MeDied as e:
            await self.me_died(str(e))
            return None, (AckCode.START_FAIL, f"ME failed: {e}")
        except QueueError as e:
            return None, (AckCode.START_FAIL, str(e))

    async def _serve_step(
        self,
        conv: Conversation,
        ack: str,
        allowed: tuple[MachineStatus, ...],
        work: Callable[[Message], Awaitable[tuple[str, str] | None]],
    ) -> bool:
        """One of 6.3.2's steps: the state checked and the work done under the state lock, refusals
        answered with `ack`. True when it was done (the caller answers ACK_OK)."""
        assert conv.first is not None
        req = conv.first.first
        async with self._state_lock:
            refusal = self._check(req, allowed)
            if refusal is None:
                refusal = await work(req)
        if refusal is not None:
            await self._refuse_now(conv, ack, *refusal)
            return False
        return True

    async def setup_run(self, conv: Conversation) -> None:
        """6.3.2.3: Idle only; recipe and op type checked; the approved recipe to the ME; status Setup."""
        assert conv.first is not None
        req = conv.first.first
        self.log.info("SETUP_RUN run %d recipe %s op %s", req.machine_run_id, req.recipe_id, req.op_type)
        if not await self._serve_step(conv, "Setup_Run_Ack", (S.IDLE,), self._setup):
            return
        self.log.info("set up run %d with recipe %s", req.machine_run_id, req.recipe_id)
        await conv.send(message("Setup_Run_Ack", ack_code=AckCode.ACK_OK))

    async def _setup(self, req: Message) -> tuple[str, str] | None:
        # The recipe is asked of the ERS first, so that the ERS looks it up while we read our table.
        fetch = asyncio.ensure_future(self.fetch_recipe(req.recipe_id))
        await asyncio.sleep(0)  # let it send before the (blocking) read
        try:
            ok = self._read(
                "SELECT 1 FROM op_machine_recipe WHERE machine_id = %s AND recipe_id = %s AND op_type = %s",
                (self.machine_id, req.recipe_id, req.op_type),
            )
        except DatabaseUnavailable:
            fetch.cancel()
            raise  # fatal (3.2.2): the module answers DB_Badrea and stops cleanly
        except DatabaseError as e:
            fetch.cancel()
            return AckCode.DB_BADREA, str(e)
        if not ok:
            fetch.cancel()
            return AckCode.REC_INVAL, f"recipe {req.recipe_id} is not for op type {req.op_type} on {self.machine_id}"
        # Listing 3: a machine set up for a run accepts no other operation until the run is over. Asked
        # now, beside the recipe's download, which does not depend on it: only the status change waits.
        accept = asyncio.ensure_future(self.set_accept_types([]))
        try:
            refusal = await self._set_up_on_me(req, fetch)
        finally:
            accepted = await accept
        if refusal is None and not accepted:
            refusal = AckCode.DB_BADUPD, "MSCHED did not take the accept types"
        if refusal is None and not await self.change_status(
            S.SETUP, expect=[S.IDLE], recipe_id=req.recipe_id, machine_run_id=req.machine_run_id
        ):
            refusal = AckCode.DB_BADUPD, "the Machine Server refused the change to Setup"
        if refusal is not None:
            if accepted:
                await self.set_accept_types(ALL_OPERATIONS)
            return refusal
        self.machine_run_id, self.recipe_id = req.machine_run_id, req.recipe_id
        return None

    async def _set_up_on_me(self, req: Message, fetch: Awaitable[tuple[Path | None, str]]) -> tuple[str, str] | None:
        """The approved recipe (`fetch`: from the ERS) to the ME, which sets up with it; the refusal, or None."""
        path, why = await fetch
        if path is None:
            await self.raise_alarm("REC_INVAL", f"{self.machine_id}: recipe {req.recipe_id} refused: {why}", wait=False)
            return AckCode.REC_INVAL, why
        answer, refusal = await self._ask_me(
            MeMessage(MessageId.SETUP_RUN, file_name=str(path), recipe_id=req.recipe_id)
        )
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return answer.ack_code or AckCode.START_FAIL, f"ME refused the setup: {answer.alarm_text}"
        return None

    async def fetch_recipe(self, recipe_id: str) -> tuple[Path | None, str]:
        """The approved version from the ERS, checksum verified, written where the ME can read it."""
        try:
            reply = await self.ask(
                "RECIPE_GET",
                message("Recipe_Fetch", recipe_id=recipe_id, machine_id=self.machine_id),
                "ers",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            return None, "the Equipment Recipe Server did not answer"
        if reply.ack_code != AckCode.ACK_OK or reply.content is None:
            return None, reply.note or f"recipe {recipe_id} refused by the ERS ({reply.ack_code})"
        digest = hashlib.sha256(reply.content.encode()).hexdigest()
        if digest != reply.checksum:
            return None, f"recipe {recipe_id} v{reply.version} checksum mismatch: the recipe was modified"
        self.recipe_dir.mkdir(parents=True, exist_ok=True)
        path = self.recipe_dir / f"{recipe_id}.v{reply.version}"
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(reply.content)
        tmp.replace(path)
        return path, ""

    async def start_run(self, conv: Conversation) -> None:
        """6.3.2.4: Setup or Setup_Shut only; the ME starts; Running (or Run_Shut)."""
        assert conv.first is not None
        req = conv.first.first
        self.log.info("START_RUN run %d", req.machine_run_id)
        if not await self._serve_step(conv, "Start_Run_Ack", (S.SETUP, S.SETUP_SHUT), self._run_on_me):
            return
        self.log.info("run %d started", req.machine_run_id)
        await conv.send(message("Start_Run_Ack", ack_code=AckCode.ACK_OK))

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

    async def _run_on_me(self, req: Message) -> tuple[str, str] | None:
        if req.machine_run_id != self.machine_run_id:
            return AckCode.START_FAIL, f"set up for run {self.machine_run_id}, not {req.machine_run_id}"
        results = self._results_path(req.machine_run_id)
        answer, refusal = await self._ask_me(
            MeMessage(MessageId.START_RUN, file_name=str(results), recipe_id=self.recipe_id or "")
        )
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return AckCode.START_FAIL, f"ME refused to start: {answer.ack_code} {answer.alarm_text}"
        # The status now, not at the check: a shutdown may have come while the ME was starting.
        target = S.RUN_SHUT if self.status == S.SETUP_SHUT else S.RUNNING
        if not await self.change_status(
            target, expect=[self.status], machine_run_id=req.machine_run_id, recipe_id=self.recipe_id
        ):
            return AckCode.DB_BADUPD, f"the Machine Server refused the change to {target}"
        return None

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

        def store(cur: Any) -> None:
            cur.executemany(  # pipelined: one round trip to the server, not one per result
                "INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) "
                "VALUES (%s, %s, %s, %s) "
                "ON CONFLICT (machine_run_id, machine_id, param) DO UPDATE SET value = EXCLUDED.value",
                [(run_id, self.machine_id, param, value) for param, value in results.items()],
            )
            # With the results, before Idle: a lot that misses our Run_Complete (we die before it goes
            # out) finds the outcome here instead of running the operation again.
            cur.execute(
                "INSERT INTO machine_run_outcome (machine_run_id, machine_id, ack_code, note) "
                "VALUES (%s, %s, %s, %s) ON CONFLICT (machine_run_id, machine_id) DO UPDATE "
                "SET ack_code = EXCLUDED.ack_code, note = EXCLUDED.note, ended_at = clock_timestamp()",
                (run_id, self.machine_id, str(code), note),
            )

        try:
            self.transaction(store)
        except DatabaseError as e:
            self.log.error("results of run %d not stored: %s (file %s kept)", run_id, e, path)
            code = AckCode.DB_BADUPD
        else:
            self.log.info("run %d: %d results stored in MACHINE_RUN_RESULT", run_id, len(results))
            if path is not None:
                path.unlink(missing_ok=True)
        if code != AckCode.ACK_OK:
            await self.raise_alarm(
                "RUN_FAIL", f"{self.machine_id}: run {run_id} failed ({code}{': ' + note if note else ''})", wait=False
            )
        self.machine_run_id = self.recipe_id = None
        if shutdown is not None:
            await self._go_shutdown(shutdown, tell_me=tell_me)
        else:
            await self.change_status(S.IDLE, note=None if code == AckCode.ACK_OK else f"run {run_id}: {code}")
        await self._announce_run(run_id, code, note)
        if shutdown is None:
            await self.set_accept_types(ALL_OPERATIONS)

    async def _announce_run(self, run_id: int, code: str, note: str | None) -> None:
        self.log.info("run %d complete (%s)%s", run_id, code, f": {note}" if note else "")
        conv = await self.bus.start(
            "RUN_COMPL",
            message("Run_Complete", machine_id=self.machine_id, machine_run_id=run_id, ack_code=code, note=note),
        )
        conv.end()

    async def download(self, conv: Conversation) -> None:
        """DNLD_ME (5.1.3): a recipe from the cell to the machine. Idle only."""
        assert conv.first is not None
        req = conv.first.first
        if not await self._serve_step(conv, "Download_Ack", (S.IDLE,), self._download):
            return
        self.log.info("recipe %s downloaded to %s", req.recipe_id, self.machine_id)
        await conv.send(message("Download_Ack", ack_code=AckCode.ACK_OK))

    async def _download(self, req: Message) -> tuple[str, str] | None:
        path, why = await self.fetch_recipe(req.recipe_id)
        if path is None:
            return AckCode.REC_INVAL, why
        answer, refusal = await self._ask_me(MeMessage(MessageId.DNLD_ME, file_name=str(path), recipe_id=req.recipe_id))
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return answer.ack_code or AckCode.START_FAIL, f"ME refused the download: {answer.alarm_text}"
        return None

    async def upload(self, conv: Conversation) -> None:
        """UPLD_ME (5.1.3): the machine's recipe back to the cell, stored by the ERS as a new version."""
        assert conv.first is not None
        req = conv.first.first
        async with self._state_lock:
            refusal = self._check(req, (S.IDLE,))
            content: str | None = None
            if refusal is None:
                refusal, content = await self._upload(req)
        if refusal is not None:
            return await self._refuse_now(conv, "Upload_Ack", *refusal)
        assert content is not None
        try:
            stored = await self.ask(
                "RECIPE_PUT",
                message("Recipe_Store", recipe_id=req.recipe_id, content=content, by=self.name),
                "ers",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            return await self._refuse_now(
                conv, "Upload_Ack", AckCode.TIMEOUT, "the Equipment Recipe Server did not answer"
            )
        self.log.info(
            "recipe %s uploaded from %s: ERS says %s, version %s",
            req.recipe_id,
            self.machine_id,
            stored.ack_code,
            stored.version,
        )
        await conv.send(message("Upload_Ack", ack_code=stored.ack_code, version=stored.version, note=stored.note))

    async def _upload(self, req: Message) -> tuple[tuple[str, str] | None, str | None]:
        answer, refusal = await self._ask_me(MeMessage(MessageId.UPLD_ME, recipe_id=req.recipe_id))
        if answer is None:
            return refusal, None
        if answer.ack_code != AckCode.ACK_OK or not answer.file_name:
            return (answer.ack_code or AckCode.START_FAIL, f"the ME returned no recipe: {answer.alarm_text}"), None
        try:
            return None, Path(answer.file_name).read_text()
        except (OSError, UnicodeDecodeError) as e:
            return (AckCode.REC_INVAL, f"the ME's recipe file {answer.file_name} is unreadable: {e}"), None
