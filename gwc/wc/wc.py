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
import logging
import math
import os
import time

from gwc.cell import read_pid
from gwc.config import Config
from gwc.errors import ConversationTimeout, DatabaseError, DatabaseUnavailable, QueueError, QueueNotOurs
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import Channel, MeMessage, MessageId
from gwc.ipc.names import Conv, Msg
from gwc.me.machine import MeState
from gwc.module import Handler, module_name
from gwc.wc.base import ABANDONED_S, ALL_OPERATIONS, ME_DEADLINE, ME_PING, SETUP_CHECK_S, S
from gwc.wc.link import MeDied, MeLink
from gwc.wc.runs import StartCancelled
from gwc.wc.steps import WCSteps


class WC(WCSteps):
    """A machine's WC. Its parts: WCBase (state, the servers), WCRuns (the ME, a run's end), WCSteps (the
    conversations served); here its life: start, shutdown, resume after a restart, the idle watch."""

    role = "wc"
    start_class = Conv.ME_START
    stop_class = Conv.ME_SHUT
    always = (Conv.ALARM_CLE,)
    # Peers a WC does not track (docs/protocol.md, *Peers a module ignores*). The other WCs: a WC
    # addresses none and starts no class one listens to (it starts RUN_COMPL and asks the servers), so
    # it need not read their beats: with N machines, N-1 fewer a heartbeat. The lot scripts: a WC only
    # answers them, and the one lot that must hear its Run_Complete is the one whose run it was, named
    # to the bus when it is sent; so no lot's sign-on, change of interest or bye wakes N WCs.
    ignored_peers = ("wc:", "lot:")

    def __init__(self, cfg: Config, name: str, log: logging.Logger, machine_id: str) -> None:
        # Before the base's __init__: it asks idle_interest(), which depends on the status.
        self.status = S.SHUTDOWN  # our copy of MACHINE_STATUS.status; the Machine Server holds the truth
        super().__init__(cfg, name, log)
        self.machine_id = machine_id
        self.machine_run_id = None
        self.recipe_id = None
        self.me = MeLink(Channel(cfg.ipc_prefix, machine_id, "wc", log), log, self._from_me)
        self.recipe_dir = cfg.var / "recipes" / machine_id
        self.results_dir = cfg.results_dir / machine_id
        self._state_lock = asyncio.Lock()  # one status-changing step at a time
        self._accept_lock = asyncio.Lock()  # accept-type changes reach MSCHED one at a time, in order
        self._accepting_none: asyncio.Future[bool] | None = None  # a setup's accepts-nothing, unanswered yet
        self._alarm_waits = {}
        self._cleared = set()  # alarm numbers seen cleared (a clear may beat our wait for it)
        self._alarm_pending = 0  # alarms of ours waiting for the operator: ME answers may take that long
        self._set_up_for = None
        self._start_note: str | None = None  # why the last ME_START failed, for ME_Ready's note
        self._resuming = False  # a restarted WC checking its ME and its run: nothing served meanwhile
        self._setup_checked = 0.0  # when the run set up was last found reserved (or not) ...
        self._unreserved_since: float | None = None  # ... and since when it is not
        self._me_pidfd: int | None = None  # the ME's process, watched for its exit

    # ----------------------------------------------------------------- module hooks

    def handlers(self) -> dict[str, Handler]:
        return {
            Conv.SETUP_RUN: self.setup_run,
            Conv.START_RUN: self.start_run,
            Conv.DNLD_ME: self.download,
            Conv.UPLD_ME: self.upload,
            Conv.ALARM_CLE: self.alarm_cleared,
        }

    def serves(self, cls: str) -> bool:
        # A machine set up before a shutdown request may still start its run (Setup_Shut, 6.3.2.4).
        return super().serves(cls) or (cls == Conv.START_RUN and self.status == S.SETUP_SHUT)

    def idle_interest(self) -> set[str]:
        extra = {Conv.START_RUN} if self.status == S.SETUP_SHUT else set()
        return super().idle_interest() | extra

    def startup_complete(self, code: str) -> Message:
        return message(Msg.ME_READY, machine_id=self.machine_id, ack_code=code, note=self._start_note)

    def shutdown_complete(self, note: str | None) -> Message:
        return message(Msg.ME_STOPPED, machine_id=self.machine_id, ack_code=AckCode.ACK_OK, note=note)

    async def run(self, start: bool = False) -> int:
        try:
            return await super().run(start)
        finally:
            self._unwatch_me_process()
            self.me.stop()

    def _watch_me_process(self) -> None:
        """Watch the ME's process by its pid file (written by whoever started it): the kernel tells its
        exit at once (a pidfd), and the next heartbeat pings the ME to confirm, so the idle pings
        (ME_PING) are left to find an ME that hangs. No pid file: the pings alone, as before."""
        self._unwatch_me_process()
        name = module_name("me", self.machine_id)
        st = read_pid(self.cfg, name)
        if not st.alive or st.pid is None:
            return
        try:
            fd = os.pidfd_open(st.pid)
        except OSError:
            return
        if read_pid(self.cfg, name).pid != st.pid:  # the pid file changed meanwhile: not that process
            os.close(fd)
            return
        self._me_pidfd = fd
        self._loop.add_reader(fd, self._me_process_exited, st.pid)

    def _unwatch_me_process(self) -> None:
        fd, self._me_pidfd = self._me_pidfd, None
        if fd is not None:
            if not self._loop.is_closed():
                self._loop.remove_reader(fd)
            os.close(fd)

    def _me_process_exited(self, pid: int) -> None:
        self._unwatch_me_process()
        self.log.warning("the ME's process (pid %d) exited: pinging it at the next heartbeat", pid)
        self.me.heard = -math.inf

    async def on_bus(self) -> None:
        self.status, self.machine_run_id, self.recipe_id = self._read_status()
        # What the ME sent while no WC listened is read now (a RUN_COMPL is completed by its own task,
        # which takes the state lock before _resume looks at the run).
        try:
            self.me.start(self._loop)
        except QueueNotOurs as e:  # someone else's queue under our name: said to the operator, never used
            self.log.error("%s", e)
            await self.raise_alarm("IPC_FOREIGN", f"{self.machine_id}: {e}"[:200], wait=False)
            raise
        self._watch_me_process()
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

    async def still_up(self) -> bool:
        """A WC the Machine Server shut down while it could not hear it (a cut cable, a long freeze) still
        counts itself Idle: on ME_START it asks, learns the machine is Shutdown, and starts it again."""
        if self.status != S.IDLE:
            return True  # in a run: its end's status change is refused and brings the Shutdown home
        try:
            reply = await self.ask(Conv.GET_STATUS, message(Msg.GET_STATUS, machine_id=self.machine_id), "ms")
        except ConversationTimeout:
            return True
        if reply.status != S.SHUTDOWN:
            return True
        self.log.warning("the Machine Server has %s Shutdown (%s): starting it again", self.machine_id, reply.note)
        self.status, self.started = S.SHUTDOWN, False
        self.bus.set_interest(self.idle_interest())
        return False

    async def _startup_machine(self) -> tuple[str, str | None]:
        if self.status != S.SHUTDOWN:
            return AckCode.NOTNOW, f"the machine is {self.status}, not Shutdown"
        self.log.info("starting machine %s: ME_START to the ME", self.machine_id)
        try:
            answer = await self._start_on_me()
        except StartCancelled as e:
            return AckCode.REQ_CANCEL, str(e)
        except (MeDied, QueueError) as e:
            await self.raise_alarm(
                "ME_DIED", f"machine side of {self.machine_id} did not answer ME_START: {e}", wait=False
            )
            return AckCode.START_FAIL, f"the ME did not start: {e}"
        if answer.ack_code != AckCode.ACK_OK:
            # Listing 3's MESTRT_FAIL ("See Error Log"), 3.2.2's alarm to turn the machine on: the operator
            # learns that the machine did not start, and why, where every alarm goes.
            why = f"{answer.ack_code} {answer.alarm_text or ''}".strip()
            await self.raise_alarm("MESTRT_FAIL", f"{self.machine_id} refused to start: {why}", wait=False)
            return AckCode.START_FAIL, f"the ME refused ME_START: {why}"
        if not await self.change_status(S.IDLE, expect=[S.SHUTDOWN]):
            return AckCode.START_FAIL, "the Machine Server refused the change to Idle"
        if not await self.set_accept_types(ALL_OPERATIONS):
            await self.change_status(S.SHUTDOWN, note="MSCHED did not take the accept types")
            return AckCode.START_FAIL, "MSCHED did not take the accept types"
        self.me.heard = time.monotonic()
        self._watch_me_process()  # a restarted ME has another process
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
        if self._resuming or not self._me_up or self.me.busy or time.monotonic() - self.me.heard < ME_PING:
            return
        try:
            answer = await self.me_request(MeMessage(MessageId.NO_MESSAGE), timeout=ME_DEADLINE)
        except (MeDied, QueueError) as e:
            if self._me_up:
                await self.me_died(str(e))
            return
        if answer.ack_code != AckCode.ACK_OK and self._me_up:
            await self.me_died(
                f"the ME answers that it is shut down ({answer.alarm_text or answer.ack_code}): "
                "it was restarted and lost the machine's state"
            )

    @property
    def _me_up(self) -> bool:
        """The ME should be up and is watched: the machine is, or it is lost (its ME looks for it)."""
        return self.status != S.SHUTDOWN or self.lost is not None

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
