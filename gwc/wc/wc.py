"""WC, the cell side of a machine interface (thesis 6.3): one program for every machine.

The WC is the machine's voice on the bus. It serves ME_START, ME_SHUT, SETUP_RUN, START_RUN,
DNLD_ME and UPLD_ME, and carries what its ME reports (alarms, run completions) to the cell. It talks
to its ME over the machine's queue pair (gwc.ipc.mq), one request at a time, each answered by an
ack. It never writes another module's tables: status changes go to the Machine Server (CHG_STATUS),
accept types to MSCHED (ACC_TYP_C), alarms to the Cell Alarm Server (ALARM_SEND), recipes come from
the Equipment Recipe Server (RECIPE_GET). It writes only MACHINE_RUN_RESULT rows of its own runs.

Its ME is watched: the WC pings it over the queues when it has heard nothing for `ME_PING` seconds;
an ME that does not answer within `ME_DEADLINE` is dead: alarm ME_DIED, machine Shutdown, and the
WC waits for the operator's next ME_START (6.3.2.1) once the ME has been restarted.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import threading
import time
from pathlib import Path
from typing import Any

from gwc.config import Config
from gwc.errors import ConversationTimeout, GwcError, QueueError, QueueTimeout
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.mq import Channel, MeMessage, MessageId
from gwc.me.results import read_results
from gwc.module import Handler, Module

ME_PING = 1.0  # ping the ME after this long without hearing from it
ME_DEADLINE = 2.0  # an ME silent this long after a ping is dead
ME_ANSWER = 10.0  # longest an ME may take to acknowledge a request (not counting operator alarms)
SERVER_TIMEOUT = 5.0  # longest a server may take to answer the WC
ALL_OPERATIONS = ["*"]
S = MachineStatus


class MeDied(GwcError):
    """The ME stopped answering."""


class WC(Module):
    role = "wc"
    start_class = "ME_START"
    stop_class = "ME_SHUT"
    always = ("ALARM_CLE",)

    def __init__(self, cfg: Config, name: str, log: logging.Logger, machine_id: str) -> None:
        super().__init__(cfg, name, log)
        self.machine_id = machine_id
        self.spec = cfg.machine(machine_id)
        self.status = S.SHUTDOWN  # our copy of MACHINE_STATUS.status; the Machine Server holds the truth
        self.machine_run_id: int | None = None
        self.busy = False  # a SETUP_RUN/START_RUN/DNLD/UPLD is between its check and its change
        self.channel = Channel(cfg.ipc_prefix, machine_id, "wc", log)
        self.recipe_dir = cfg.var / "recipes" / machine_id
        self._me_lock = asyncio.Lock()
        self._me_answer: asyncio.Future[MeMessage] | None = None
        self._me_heard = time.monotonic()
        self._alarm_waits: dict[int, asyncio.Future[None]] = {}
        self._alarm_pending = 0  # alarms of ours waiting for the operator: ME answers may take that long
        self._reader: threading.Thread | None = None
        self._reader_stop = threading.Event()

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
        return message("ME_Ready", machine_id=self.machine_id, ack_code=code)

    def shutdown_complete(self, note: str | None) -> Message:
        return message("ME_Stopped", machine_id=self.machine_id, ack_code=AckCode.ACK_OK, note=note)

    async def run(self, start: bool = False) -> int:
        try:
            return await super().run(start)
        finally:
            self._reader_stop.set()
            if self._reader:
                self._reader.join(2)
            self.channel.close()

    async def on_bus(self) -> None:
        self.channel.open()
        self._reader = threading.Thread(target=self._read_me, name="me-reader", daemon=True)
        self._reader.start()
        self.status, self.machine_run_id = self._read_status()
        if self.status != S.SHUTDOWN:
            # A WC restarted while its machine was up resumes it (the ME kept its queue); the ME
            # watch below finds out soon enough if the ME did not survive.
            self.log.warning("machine %s is %s (run %s): resuming it", self.machine_id, self.status,
                             self.machine_run_id)
            self.started = self.status not in (S.SETUP_SHUT, S.RUN_SHUT)
            self.bus.set_interest(self.busy_interest() if self.started else self.idle_interest())
            self._me_heard = 0.0

    async def on_startup(self) -> str:
        """6.3.2.1: ME_START to the ME (homing alarm passed on and cleared), all operations, Idle."""
        if self.status != S.SHUTDOWN:
            return AckCode.NOTNOW
        self.channel.drain()
        try:
            answer = await self.me_request(MeMessage(MessageId.ME_START))
        except (MeDied, QueueError) as e:
            self.log.error("ME did not start: %s", e)
            return AckCode.START_FAIL
        if answer.ack_code != AckCode.ACK_OK:
            self.log.error("ME refused ME_START: %s %s", answer.ack_code, answer.alarm_text)
            return AckCode.START_FAIL
        if not await self.change_status(S.IDLE, expect=[S.SHUTDOWN]):
            return AckCode.START_FAIL
        if not await self.set_accept_types(ALL_OPERATIONS):
            await self.change_status(S.SHUTDOWN)
            return AckCode.START_FAIL
        self._me_heard = time.monotonic()
        return AckCode.ACK_OK

    async def on_shutdown(self) -> str | None:
        """6.3.2.2: Idle shuts down at once; Setup and Running shut down when their run is over."""
        await self.set_accept_types([])
        if self.status == S.SETUP:
            await self.change_status(S.SETUP_SHUT, expect=[S.SETUP])
            self.bus.set_interest(self.idle_interest())
            return "shutdown pending: the machine is set up; it shuts down after its run"
        if self.status == S.RUNNING:
            await self.change_status(S.RUN_SHUT, expect=[S.RUNNING])
            return "shutdown pending: the machine shuts down when its run completes"
        if self.status in (S.SETUP_SHUT, S.RUN_SHUT):
            return "shutdown already pending"
        await self._go_shutdown("operator shutdown")
        return None

    async def on_idle(self) -> None:
        """Watch the ME: ping it when quiet; declare it dead when a ping goes unanswered."""
        if self.status == S.SHUTDOWN or self._me_lock.locked():
            if self._me_lock.locked() and not self._alarm_pending and \
                    time.monotonic() - self._me_heard > ME_ANSWER + ME_DEADLINE:
                self.log.error("ME has not answered for %.1fs", time.monotonic() - self._me_heard)
            return
        if time.monotonic() - self._me_heard < ME_PING:
            return
        try:
            await self.me_request(MeMessage(MessageId.NO_MESSAGE), timeout=ME_DEADLINE)
        except (MeDied, QueueError) as e:
            await self.me_died(str(e))

    # ----------------------------------------------------------------- the ME side

    def _read_me(self) -> None:
        """Thread: block on the ME's queue and hand every message to the event loop."""
        loop = self._loop
        while not self._reader_stop.is_set():
            try:
                msg = self.channel.receive(timeout=0.2)
            except QueueTimeout:
                continue
            except QueueError as e:
                loop.call_soon_threadsafe(self.log.warning, "garbled message from ME dropped: %s", e)
                continue
            loop.call_soon_threadsafe(self._from_me, msg)

    @property
    def _loop(self) -> asyncio.AbstractEventLoop:
        loop = self.bus._loop
        assert loop is not None
        return loop

    def _from_me(self, msg: MeMessage) -> None:
        self._me_heard = time.monotonic()
        if msg.message_id == MessageId.CELL_ALAR:
            self._spawn(self.alarm_action(msg))
        elif msg.message_id == MessageId.RUN_COMPL:
            self._spawn(self.run_complete(msg))
        elif self._me_answer is not None and not self._me_answer.done():
            self._me_answer.set_result(msg)
        else:
            self.log.warning("unexpected %s from ME dropped", msg.message_id.name)

    def _spawn(self, coro: Any) -> None:
        task = self._loop.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def me_request(self, msg: MeMessage, timeout: float = ME_ANSWER) -> MeMessage:
        """Send one request to the ME and wait for its answer (one at a time, as the queue protocol is)."""
        async with self._me_lock:
            self._me_answer = self._loop.create_future()
            try:
                self.channel.send(msg)
                while True:
                    try:
                        return await asyncio.wait_for(asyncio.shield(self._me_answer), timeout)
                    except asyncio.TimeoutError:
                        if not self._alarm_pending:  # an operator alarm may hold the ME up: wait for it
                            raise MeDied(f"ME did not answer {msg.message_id.name} within {timeout:.1f}s") from None
            finally:
                self._me_answer = None

    async def me_died(self, why: str) -> None:
        self.log.error("ME of %s is dead (%s): alarm, machine Shutdown", self.machine_id, why)
        await self.raise_alarm("ME_DIED", f"machine side of {self.machine_id} stopped answering: {why}", wait=False)
        if self.started:
            self.started = False
        await self._go_shutdown(f"ME died: {why}", tell_me=False)

    async def _go_shutdown(self, note: str, tell_me: bool = True) -> None:
        """Machine to Shutdown: no operations accepted, status Shutdown, ME told (6.3.2.2)."""
        self.started = False
        self.busy = False
        await self.set_accept_types([])
        await self.change_status(S.SHUTDOWN, note=note)
        self.bus.set_interest(self.idle_interest())
        if tell_me:
            try:
                answer = await self.me_request(MeMessage(MessageId.ME_SHUT))
                if answer.ack_code != AckCode.ACK_OK:
                    self.log.warning("ME answered ME_SHUT with %s", answer.ack_code)
            except (MeDied, QueueError) as e:
                self.log.warning("ME did not acknowledge ME_SHUT: %s", e)

    # ----------------------------------------------------------------- asking the servers

    def _read_status(self) -> tuple[MachineStatus, int | None]:
        row = self.db().execute("SELECT status, machine_run_id FROM machine_status WHERE machine_id = %s",
                                (self.machine_id,)).fetchone()
        self.db().rollback()
        return (MachineStatus(row[0]), row[1]) if row else (S.SHUTDOWN, None)

    async def change_status(self, status: MachineStatus, expect: list[MachineStatus] | None = None,
                            **fields: Any) -> bool:
        """Ask the Machine Server to change our status; keep our copy in step when it agrees."""
        try:
            answer = await self.ask("CHG_STATUS", message(
                "Change_Status", machine_id=self.machine_id, status=status,
                expect=[str(s) for s in expect] if expect else None, **fields), "ms", SERVER_TIMEOUT)
        except ConversationTimeout:
            self.log.error("Machine Server did not answer the change to %s", status)
            return False
        if answer.ack_code != AckCode.ACK_OK:
            self.log.error("Machine Server refused %s: %s %s", status, answer.ack_code, answer.note or "")
            if answer.status:
                self.status = MachineStatus(answer.status)
            return False
        self.status = status
        return True

    async def set_accept_types(self, op_types: list[str]) -> bool:
        try:
            answer = await self.ask("ACC_TYP_C", message("Chg_Accept_Type", machine_id=self.machine_id,
                                                         op_types=op_types), "msched", SERVER_TIMEOUT)
        except ConversationTimeout:
            self.log.error("MSCHED did not answer the accept-type change to %s", op_types or "none")
            return False
        if answer.ack_code != AckCode.ACK_OK:
            self.log.error("MSCHED refused accept types %s: %s", op_types, answer.ack_code)
            return False
        return True

    async def raise_alarm(self, alarm_id: str, text: str, wait: bool) -> bool:
        """6.3.2.8: pass an alarm to the CAS; when `wait`, hold until the operator clears it."""
        while True:
            try:
                answer = await self.ask("ALARM_SEND", message("Alarm_Send", alarm_id=alarm_id, alarm_text=text,
                                                              machine_id=self.machine_id, raised_by=self.name),
                                        "cas", SERVER_TIMEOUT)
                break
            except ConversationTimeout:
                if not wait:
                    self.log.error("Cell Alarm Server did not take alarm %s", alarm_id)
                    return False
                self.log.error("Cell Alarm Server did not take alarm %s: trying again", alarm_id)
        if answer.ack_code != AckCode.ACK_OK or answer.alarm_no is None:
            self.log.error("Cell Alarm Server refused alarm %s: %s", alarm_id, answer.ack_code)
            return False
        if not wait:
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
        waiter = self._alarm_waits.get(clear.alarm_no)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def alarm_action(self, msg: MeMessage) -> None:
        """An alarm from the ME: to the CAS, wait for the operator, then let the ME continue."""
        self._alarm_pending += 1
        try:
            alarm_id = msg.alarm_text or "UNKNOWN"
            text = self._alarm_text(alarm_id)
            cleared = await self.raise_alarm(alarm_id, text, wait=True)
            self.channel.send(MeMessage(MessageId.ALARM_CLEAR, alarm_text=alarm_id,
                                        ack_code=AckCode.ACK_OK if cleared else AckCode.START_FAIL))
        except QueueError as e:
            self.log.error("could not tell the ME its alarm was cleared: %s", e)
        finally:
            self._alarm_pending -= 1
            self._me_heard = time.monotonic()

    def _alarm_text(self, alarm_id: str) -> str:
        row = self.db().execute("SELECT alarm_text FROM alarm_description WHERE alarm_id = %s",
                                (alarm_id,)).fetchone()
        self.db().rollback()
        if row is None:
            self.log.warning("alarm %s is not in ALARM_DESCRIPTION: passing it on as unknown", alarm_id)
            return f"unknown alarm {alarm_id} from {self.machine_id}"
        return f"{self.machine_id}: {row[0]}"

    # ----------------------------------------------------------------- the conversations served

    async def _refuse_now(self, conv: Conversation, ack: str, code: str, note: str) -> None:
        self.log.info("refused %s: %s (%s)", conv.cls, code, note)
        await conv.send(message(ack, ack_code=code, note=note))

    def _claim(self, conv: Conversation, allowed: tuple[MachineStatus, ...]) -> str | None:
        """Check the machine may do this now and mark it busy, with no await in between."""
        assert conv.first is not None
        req = conv.first.first
        if req.machine_id != self.machine_id:
            return f"this is the WC of {self.machine_id}, not {req.machine_id}"
        if self.busy or self.status not in allowed:
            return f"machine is {self.status}" + (" and busy" if self.busy else "")
        self.busy = True
        return None

    async def setup_run(self, conv: Conversation) -> None:
        """6.3.2.3: Idle only; recipe and op type checked; the approved recipe to the ME; status Setup."""
        assert conv.first is not None
        req = conv.first.first
        why = self._claim(conv, (S.IDLE,))
        if why:
            return await self._refuse_now(conv, "Setup_Run_Ack", AckCode.NOTNOW, why)
        try:
            code, note = await self._setup(req)
        finally:
            self.busy = False
        if code != AckCode.ACK_OK:
            return await self._refuse_now(conv, "Setup_Run_Ack", code, note)
        self.log.info("set up run %d with recipe %s", req.machine_run_id, req.recipe_id)
        await conv.send(message("Setup_Run_Ack", ack_code=AckCode.ACK_OK))

    async def _setup(self, req: Message) -> tuple[str, str]:
        ok = self.db().execute(
            "SELECT 1 FROM op_machine_recipe WHERE machine_id = %s AND recipe_id = %s AND op_type = %s",
            (self.machine_id, req.recipe_id, req.op_type)).fetchone()
        self.db().rollback()
        if not ok:
            return AckCode.REC_INVAL, f"recipe {req.recipe_id} is not for op type {req.op_type} on {self.machine_id}"
        path, why = await self.fetch_recipe(req.recipe_id)
        if path is None:
            await self.raise_alarm("REC_INVAL", f"{self.machine_id}: recipe {req.recipe_id} refused: {why}", wait=False)
            return AckCode.REC_INVAL, why
        try:
            answer = await self.me_request(MeMessage(MessageId.SETUP_RUN, file_name=str(path), recipe_id=req.recipe_id))
        except (MeDied, QueueError) as e:
            await self.me_died(str(e))
            return AckCode.START_FAIL, f"ME failed: {e}"
        if answer.ack_code != AckCode.ACK_OK:
            return answer.ack_code or AckCode.START_FAIL, f"ME refused the setup: {answer.alarm_text}"
        if not await self.change_status(S.SETUP, expect=[S.IDLE], recipe_id=req.recipe_id,
                                        machine_run_id=req.machine_run_id):
            return AckCode.DB_BADUPD, "the Machine Server refused the change to Setup"
        self.machine_run_id = req.machine_run_id
        return AckCode.ACK_OK, ""

    async def fetch_recipe(self, recipe_id: str) -> tuple[Path | None, str]:
        """The approved version from the ERS, checksum verified, written where the ME can read it."""
        try:
            reply = await self.ask("RECIPE_GET", message("Recipe_Fetch", recipe_id=recipe_id,
                                                         machine_id=self.machine_id), "ers", SERVER_TIMEOUT)
        except ConversationTimeout:
            return None, "the Equipment Recipe Server did not answer"
        if reply.ack_code != AckCode.ACK_OK or reply.content is None:
            return None, reply.note or f"recipe {recipe_id} refused by the ERS ({reply.ack_code})"
        digest = hashlib.sha256(reply.content.encode()).hexdigest()
        if digest != reply.checksum:
            return None, f"recipe {recipe_id} v{reply.version} checksum mismatch: the recipe was modified"
        self.recipe_dir.mkdir(parents=True, exist_ok=True)
        path = self.recipe_dir / f"{recipe_id}.v{reply.version}"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(reply.content)
        tmp.replace(path)
        return path, ""

    async def start_run(self, conv: Conversation) -> None:
        """6.3.2.4: Setup or Setup_Shut only; the ME starts; Running (or Run_Shut) with its start time."""
        assert conv.first is not None
        req = conv.first.first
        why = self._claim(conv, (S.SETUP, S.SETUP_SHUT))
        if why:
            return await self._refuse_now(conv, "Start_Run_Ack", AckCode.NOTNOW, why)
        try:
            if req.machine_run_id != self.machine_run_id:
                return await self._refuse_now(conv, "Start_Run_Ack", AckCode.START_FAIL,
                                              f"set up for run {self.machine_run_id}, not {req.machine_run_id}")
            shutting = self.status == S.SETUP_SHUT
            try:
                answer = await self.me_request(MeMessage(MessageId.START_RUN, recipe_id=str(req.machine_run_id)))
            except (MeDied, QueueError) as e:
                await self.me_died(str(e))
                return await self._refuse_now(conv, "Start_Run_Ack", AckCode.START_FAIL, f"ME failed: {e}")
            if answer.ack_code != AckCode.ACK_OK:
                return await self._refuse_now(conv, "Start_Run_Ack", AckCode.START_FAIL,
                                              f"ME refused to start: {answer.ack_code} {answer.alarm_text}")
            target = S.RUN_SHUT if shutting else S.RUNNING
            if not await self.change_status(target, expect=[S.SETUP_SHUT if shutting else S.SETUP],
                                            machine_run_id=req.machine_run_id):
                return await self._refuse_now(conv, "Start_Run_Ack", AckCode.DB_BADUPD,
                                              f"the Machine Server refused the change to {target}")
        finally:
            self.busy = False
        self.log.info("run %d started", req.machine_run_id)
        await conv.send(message("Start_Run_Ack", ack_code=AckCode.ACK_OK))

    async def run_complete(self, msg: MeMessage) -> None:
        """6.3.2.7: results into MACHINE_RUN_RESULT, file removed, Run_Complete on the bus, Idle again."""
        run_id = self.machine_run_id
        if self.status not in (S.RUNNING, S.RUN_SHUT) or run_id is None:
            self.log.warning("RUN_COMPL from ME while %s: ignored", self.status)
            return
        code = msg.ack_code or AckCode.ACK_OK
        path = Path(msg.file_name)
        try:
            results = read_results(path) if msg.file_name else {}
        except (OSError, ValueError) as e:
            self.log.error("results file %s unreadable: %s", path, e)
            results, code = {}, AckCode.RUN_FAIL

        def store(cur: Any) -> None:
            for param, value in results.items():
                cur.execute(
                    "INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) VALUES (%s, %s, %s, %s)"
                    " ON CONFLICT (machine_run_id, machine_id, param) DO UPDATE SET value = EXCLUDED.value",
                    (run_id, self.machine_id, param, value))

        self.transaction(store)
        if msg.file_name:
            path.unlink(missing_ok=True)
        shutting = self.status == S.RUN_SHUT
        self.machine_run_id = None
        note = "run failed" if code != AckCode.ACK_OK else None
        if shutting:
            await self._go_shutdown("shutdown after run")
        else:
            await self.change_status(S.IDLE, note=note)
        self.log.info("run %d complete (%s, %d results)", run_id, code, len(results))
        conv = await self.bus.start("RUN_COMPL", message("Run_Complete", machine_id=self.machine_id,
                                                         machine_run_id=run_id, ack_code=code))
        conv.end()
        if not shutting:
            await self.set_accept_types(ALL_OPERATIONS)

    async def download(self, conv: Conversation) -> None:
        """6.3.2.6 (the thesis's names are crossed): a recipe from the cell to the machine. Idle only."""
        assert conv.first is not None
        req = conv.first.first
        why = self._claim(conv, (S.IDLE,))
        if why:
            return await self._refuse_now(conv, "Download_Ack", AckCode.NOTNOW, why)
        try:
            path, why = await self.fetch_recipe(req.recipe_id)
            if path is None:
                return await self._refuse_now(conv, "Download_Ack", AckCode.REC_INVAL, why)
            answer = await self.me_request(MeMessage(MessageId.DNLD_ME, file_name=str(path), recipe_id=req.recipe_id))
        except (MeDied, QueueError) as e:
            await self.me_died(str(e))
            return await self._refuse_now(conv, "Download_Ack", AckCode.START_FAIL, f"ME failed: {e}")
        finally:
            self.busy = False
        await conv.send(message("Download_Ack", ack_code=answer.ack_code or AckCode.ACK_OK))

    async def upload(self, conv: Conversation) -> None:
        """6.3.2.5: the machine's recipe back to the cell, stored by the ERS as a new version. Idle only."""
        assert conv.first is not None
        req = conv.first.first
        why = self._claim(conv, (S.IDLE,))
        if why:
            return await self._refuse_now(conv, "Upload_Ack", AckCode.NOTNOW, why)
        try:
            answer = await self.me_request(MeMessage(MessageId.UPLD_ME, recipe_id=req.recipe_id))
        except (MeDied, QueueError) as e:
            await self.me_died(str(e))
            return await self._refuse_now(conv, "Upload_Ack", AckCode.START_FAIL, f"ME failed: {e}")
        finally:
            self.busy = False
        if answer.ack_code != AckCode.ACK_OK or not answer.file_name:
            return await self._refuse_now(conv, "Upload_Ack", answer.ack_code or AckCode.START_FAIL,
                                          "the ME returned no recipe")
        content = Path(answer.file_name).read_text()
        stored = await self.ask("RECIPE_PUT", message("Recipe_Store", recipe_id=req.recipe_id, content=content,
                                                      by=self.name), "ers", SERVER_TIMEOUT)
        await conv.send(message("Upload_Ack", ack_code=stored.ack_code, version=stored.version))
