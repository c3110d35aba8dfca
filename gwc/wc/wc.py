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
and never handled, and the ME says whether it is still running it (gwc/wc/me_side.py, MeSide._resume).
"""

from __future__ import annotations

import logging
from collections.abc import Coroutine
from typing import Any

from gwc.config import Config
from gwc.errors import QueueNotOurs
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module
from gwc.wc.base import MachineState, ServerCalls
from gwc.wc.me_side import MeSide
from gwc.wc.steps import Steps


class WC(Module):
    """A machine's WC: a Module whose conversation handlers are here. It holds its parts: the machine's
    state (MachineState), its calls to the servers (ServerCalls), its ME side (MeSide: the queue link,
    a run's end, the machine lost and back, a restart taken up) and its steps' work (Steps)."""

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
        self.state = MachineState(machine_id, cfg.var / "recipes" / machine_id, cfg.results_dir / machine_id)
        super().__init__(cfg, name, log)
        self.servers = ServerCalls(self, self.state)
        self.me_side = MeSide(self, self.state, self.servers)
        self.steps = Steps(self, self.state, self.servers, self.me_side)
        self._start_note: str | None = None  # why the last ME_START failed, for ME_Ready's note

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
        return super().serves(cls) or (cls == Conv.START_RUN and self.state.status == MachineStatus.SETUP_SHUT)

    def idle_interest(self) -> set[str]:
        extra = {Conv.START_RUN} if self.state.status == MachineStatus.SETUP_SHUT else set()
        return super().idle_interest() | extra

    def startup_complete(self, code: str) -> Message:
        return message(Msg.ME_READY, machine_id=self.state.machine_id, ack_code=code, note=self._start_note)

    def shutdown_complete(self, note: str | None) -> Message:
        return message(Msg.ME_STOPPED, machine_id=self.state.machine_id, ack_code=AckCode.ACK_OK, note=note)

    async def run(self, start: bool = False) -> int:
        try:
            return await super().run(start)
        finally:
            self.me_side.stop()

    async def on_bus(self) -> None:
        state = self.state
        state.status, state.machine_run_id, state.recipe_id = self.servers.read_status()
        # What the ME sent while no WC listened is read now (a RUN_COMPL is completed by its own task,
        # which takes the state lock before the resume looks at the run).
        try:
            self.me_side.start()
        except QueueNotOurs as e:  # someone else's queue under our name: said to the operator, never used
            self.log.error("%s", e)
            await self.servers.raise_alarm("IPC_FOREIGN", f"{state.machine_id}: {e}"[:200], wait=False)
            raise
        if state.status != MachineStatus.SHUTDOWN:
            self.log.warning(
                "machine %s is %s (run %s): resuming it", state.machine_id, state.status, state.machine_run_id
            )
            self.me_side.resume_soon()

    async def on_startup(self) -> str:
        """6.3.2.1: ME_START to the ME (homing alarm passed on and cleared), Idle, all operations."""
        code, self._start_note = await self.me_side.start_machine()
        if code != AckCode.ACK_OK:
            self.log.error("machine %s not started: %s (%s)", self.state.machine_id, code, self._start_note)
        return code

    def cancel_start(self) -> Coroutine[Any, Any, str] | None:
        """A stop while ME_START is out (the machine waits to be homed): the start is cancelled."""
        return self.me_side.cancel_start()

    async def still_up(self) -> bool:
        """A WC the Machine Server shut down while it could not hear it (a cut cable, a long freeze) still
        counts itself Idle: on ME_START it asks, learns the machine is Shutdown, and starts it again."""
        state = self.state
        if state.status != MachineStatus.IDLE:
            return True  # in a run: its end's status change is refused and brings the Shutdown home
        reply = await self.servers.machine_server_status()
        if reply is None or reply.status != MachineStatus.SHUTDOWN:
            return True
        self.log.warning("the Machine Server has %s Shutdown (%s): starting it again", state.machine_id, reply.note)
        state.status, self.started = MachineStatus.SHUTDOWN, False
        self.bus.set_interest(self.idle_interest())
        return False

    async def on_shutdown(self) -> str | None:
        """6.3.2.2: Idle shuts down at once; Setup and Running shut down when their run is over."""
        state, servers = self.state, self.servers
        async with state.lock:
            await servers.set_accept_types([])
            if state.status == MachineStatus.SETUP:
                await servers.change_status(MachineStatus.SETUP_SHUT, expect=[MachineStatus.SETUP])
                self.bus.set_interest(self.idle_interest())
                self.log.info("shutdown pending: the machine is set up; it shuts down after its run")
                return "shutdown pending: the machine is set up; it shuts down after its run"
            if state.status == MachineStatus.RUNNING:
                await servers.change_status(MachineStatus.RUN_SHUT, expect=[MachineStatus.RUNNING])
                self.log.info("shutdown pending: the machine shuts down when its run completes")
                return "shutdown pending: the machine shuts down when its run completes"
            if state.status in (MachineStatus.SETUP_SHUT, MachineStatus.RUN_SHUT):
                return "shutdown already pending"
            await self.me_side.go_shutdown("operator shutdown")
            return None

    async def on_idle(self) -> None:
        """Give up an abandoned setup; watch the ME: ping it when quiet; declare it dead when a ping goes
        unanswered."""
        await self.steps.give_up_abandoned_setup()
        await self.me_side.ping_if_quiet()

    # ----------------------------------------------------------------- the conversations served

    async def setup_run(self, conv: Conversation) -> None:
        """6.3.2.3: Idle only; reservation, recipe and op type checked; the approved recipe to the ME;
        status Setup (asked beside the ME's setup: docs/machine-interface.md, *The order of a run's steps*).
        A request that names no recipe gets this machine's for the op type (OP_MACHINE_RECIPE), named in
        the answer. One that says `start` is started as soon as it is set up, as START_RUN would, and
        answered once Running: the lot's START_RUN round trip saved (docs/lot-scripts.md)."""
        assert conv.first is not None
        req = conv.first.first
        self.log.info(
            "SETUP_RUN run %d recipe %s op %s%s",
            req.machine_run_id,
            req.recipe_id or "(ours)",
            req.op_type,
            " and start" if req.start else "",
        )
        entity, refusal = self.steps.asking_entity(conv)
        if refusal is not None:
            await self.steps.refuse_now(conv, Msg.SETUP_RUN_ACK, *refusal)
            return
        if not await self.steps.serve_step(
            conv, Msg.SETUP_RUN_ACK, (MachineStatus.IDLE,), lambda r: self.steps.setup(r, entity)
        ):
            return
        self.state.set_up_for = (conv.initiator, req.machine_run_id)
        self.log.info(
            "set up run %d with recipe %s%s", req.machine_run_id, self.state.recipe_id, ", started" if req.start else ""
        )
        await conv.send(message(Msg.SETUP_RUN_ACK, ack_code=AckCode.ACK_OK, recipe_id=self.state.recipe_id))

    async def start_run(self, conv: Conversation) -> None:
        """6.3.2.4: Setup or Setup_Shut only; the ME starts; Running (or Run_Shut)."""
        assert conv.first is not None
        req = conv.first.first
        self.log.info("START_RUN run %d", req.machine_run_id)
        refusal = await self.steps.not_reserved(conv)
        if refusal is not None:
            await self.steps.refuse_now(conv, Msg.START_RUN_ACK, *refusal)
            return
        if not await self.steps.serve_step(
            conv, Msg.START_RUN_ACK, (MachineStatus.SETUP, MachineStatus.SETUP_SHUT), self.steps.run_on_me
        ):
            return
        self.log.info("run %d started", req.machine_run_id)
        await conv.send(message(Msg.START_RUN_ACK, ack_code=AckCode.ACK_OK))

    async def download(self, conv: Conversation) -> None:
        """DNLD_ME (5.1.3): a recipe from the cell to the machine. Idle only."""
        assert conv.first is not None
        req = conv.first.first
        refusal = await self.steps.not_held(conv)
        if refusal is not None:
            return await self.steps.refuse_now(conv, Msg.DOWNLOAD_ACK, *refusal)
        if not await self.steps.serve_step(conv, Msg.DOWNLOAD_ACK, (MachineStatus.IDLE,), self.steps.download):
            return
        self.log.info("recipe %s downloaded to %s", req.recipe_id, self.state.machine_id)
        await conv.send(message(Msg.DOWNLOAD_ACK, ack_code=AckCode.ACK_OK))

    async def upload(self, conv: Conversation) -> None:
        """UPLD_ME (5.1.3): the machine's recipe back to the cell, stored by the ERS as a new version."""
        assert conv.first is not None
        req = conv.first.first
        refusal = await self.steps.not_held(conv)
        if refusal is not None:
            return await self.steps.refuse_now(conv, Msg.UPLOAD_ACK, *refusal)
        async with self.state.lock:
            refusal = self.steps.check(req, (MachineStatus.IDLE,))
            content: str | None = None
            if refusal is None:
                refusal, content = await self.steps.upload(req)
        if refusal is not None:
            return await self.steps.refuse_now(conv, Msg.UPLOAD_ACK, *refusal)
        assert content is not None
        by = conv.initiator if conv.initiator.startswith("lot:") else self.name
        stored = await self.servers.store_recipe(req.recipe_id, content, by)
        if stored is None:
            return await self.steps.refuse_now(
                conv, Msg.UPLOAD_ACK, AckCode.TIMEOUT, "the Equipment Recipe Server did not answer"
            )
        self.log.info(
            "recipe %s uploaded from %s: ERS says %s, version %s",
            req.recipe_id,
            self.state.machine_id,
            stored.ack_code,
            stored.version,
        )
        await conv.send(message(Msg.UPLOAD_ACK, ack_code=stored.ack_code, version=stored.version, note=stored.note))

    async def alarm_cleared(self, conv: Conversation) -> None:
        """ALARM_CLE: an alarm cleared; a step of ours waiting for it goes on."""
        assert conv.first is not None
        clear = conv.first.first
        if clear.machine_id not in (None, self.state.machine_id):
            return
        self.servers.done_waiting(clear.alarm_no)
