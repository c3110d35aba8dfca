"""MSCHED, the machine scheduler (thesis 6.2, Listing 2): the only module that reserves machines.

Conversation handlers check a message, hand the database work to the step worker (its part
`steps`, gwc.msched.worker) and answer when it is done. The worker runs every pending change as ONE
transaction followed by one scheduling pass (gwc.msched.store.Step), in a thread while the event
loop keeps serving the bus; under load, many changes share a transaction, which is where the
scheduler's throughput comes from. After the commit the worker hands each outcome to whoever
tells the entity: the MACH_REQ conversation's own task when it is still waiting here, else a
teller task that resumes the conversation stored with the request (after a restart). Waiting for
a Request_Comp_Ack happens in those tasks, with a deadline: a dead entity never holds up the
scheduler.

SHUTDOWN answers every waiting request NO_MACHINE and waits for the acknowledgements (6.2.4.2).
Being stopped (SIGTERM) or killed keeps the queue: the next MSCHED carries on from the database.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

import psycopg

from gwc.config import Config
from gwc.db import Statement
from gwc.errors import DatabaseUnavailable, GwcError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.module import Module
from gwc.msched import store
from gwc.msched.policy import make_policy
from gwc.msched.store import Outcome
from gwc.msched.worker import StepWorker
from gwc.retry import Deadline

LOCK_WAIT_S = 5.0  # a killed predecessor's database session takes a moment to go
DEFAULT_SWEEP_S = 5.0

T = TypeVar("T")


class SchedulerLocked(DatabaseUnavailable):
    """Another MSCHED holds the scheduler lock: this one cannot use the database (yet)."""


class Msched(Module):
    """The machine scheduler; `clean` (gwc run msched --clean) empties its tables at start, as the thesis did."""

    role = "msched"

    def __init__(self, cfg: Config, name: str, log: logging.Logger, clean: bool = False) -> None:
        super().__init__(cfg, name, log)
        self.clean = clean
        self.policy = make_policy(cfg)
        opts = cfg.raw.get("msched", {})
        # How long an entity has to acknowledge a Machine_Req_Comp: the bus's whole retry window and then some.
        self.ack_timeout = float(opts.get("ack_timeout", cfg.bus.retry_deadline + cfg.bus.reply_timeout))
        self.sweep_s = float(opts.get("sweep_s", DEFAULT_SWEEP_S))
        self.steps = StepWorker(self.database, self.policy, log, self._dispatch)
        self._waiters: dict[str, asyncio.Future[Outcome]] = {}  # MACH_REQ conversation id -> its outcome
        self._acks: dict[int, asyncio.Future[None]] = {}  # request_key -> done when its Comp is acknowledged
        self._stopping = False
        self._last_sweep = time.monotonic()

    def handlers(self) -> dict[str, Any]:
        return {
            Conv.MACH_REQ: self.machine_request,
            Conv.CANCEL_RE: self.cancel_request,
            Conv.UPD_ME_ST: self.update_me_status,
            Conv.ACC_TYP_C: self.accept_type_change,
            Conv.UNRESERVE: self.unreserve,
        }

    # ------------------------------------------------------------------ lifecycle

    def stop(self, code: int = 0) -> None:
        self._stopping = True
        super().stop(code)

    async def on_bus(self) -> None:
        self.spawn(self.steps.run())  # cancelled with the module's other tasks when it stops

    def on_connect(self, conn: Any) -> None:
        """One MSCHED per database: a session lock, freed by PostgreSQL when its holder dies. Taken
        on every connection, for a connection lost (the database restarted) loses it."""
        if not conn.execute("select pg_try_advisory_lock(hashtext('gwc.msched'))").fetchone()[0]:
            conn.close()
            raise SchedulerLocked("another MSCHED holds the scheduler lock in this database")
        conn.commit()

    def transaction(self, fn: Callable[[psycopg.Cursor[Any]], T]) -> T:
        """Module.transaction, one user of the connection at a time: the step thread or the event loop."""
        with self.steps.lock:
            return super().transaction(fn)

    async def on_startup(self) -> str:
        if not await self._lock():
            self.log.error("another MSCHED holds the scheduler lock in this database: not starting")
            return AckCode.START_FAIL
        owed = await self.steps.submit(lambda s: s.startup(self.clean))
        if self.clean:
            self.log.info("--clean: REQUEST_MACHINES, RESERVED_MACHINES and the owed answers were emptied")
        owed = [o for o in owed if o.request_key not in self._acks]
        if owed:
            self.log.info("resending %d answer(s) not acknowledged before the restart", len(owed))
            self._dispatch(owed)
        queued, reserved = self.transaction(
            lambda cur: (
                cur.execute(
                    "select (select count(distinct request_key) from request_machines), "
                    "(select count(*) from reserved_machines)"
                ).fetchone()
                or (0, 0)
            )
        )
        self.log.info("policy %s; %d request(s) queued, %d machine(s) reserved", self.policy.name, queued, reserved)
        return AckCode.ACK_OK

    async def on_shutdown(self) -> str | None:
        if self._stopping:
            self.log.info("stopping: queued requests and reservations stay for the next start")
            return None
        n = await self.steps.submit(lambda s: s.shutdown_all("MSCHED shut down"))
        pending = list(self._acks.values())
        if pending:
            await asyncio.wait(pending, timeout=self.ack_timeout + 1)
        self.log.info("shutdown: %d waiting request(s) answered NO_MACHINE", n)
        return f"{n} waiting request(s) answered NO_MACHINE"

    async def on_idle(self) -> None:
        if self.started and time.monotonic() - self._last_sweep >= self.sweep_s:
            self._last_sweep = time.monotonic()
            if self._sweep_has_work():
                self.steps.submit(lambda s: s.sweep(), wait=False)

    def _sweep_has_work(self) -> bool:
        """(store.SWEEP_WORK) One read, alone; a read that fails says yes: the step then meets the failure.
        While a step runs or waits there is work, and the loop does not wait for the connection."""
        if self.steps.busy:
            return True
        try:
            return bool(self.transaction(Statement(store.SWEEP_WORK))[0])
        except GwcError as e:
            self.log.debug("sweep's look at the queue failed (%s): sweeping", e)
            return True

    async def on_database_back(self, down_for: float) -> None:
        """Whatever happened meanwhile (a lot that finished, a machine that went): sweep at once."""
        self.steps.submit(lambda s: s.sweep(), wait=False)

    async def _lock(self) -> bool:
        """Connect (on_connect takes the lock); a killed predecessor's session takes a moment to go."""
        try:
            self.db()
        except SchedulerLocked:
            return await self.wait_database(Deadline(LOCK_WAIT_S))
        return True

    # ------------------------------------------------------------------ conversations

    async def machine_request(self, conv: Conversation) -> None:
        """MACH_REQ: queue the request, answer Machine_Req_Ack, and later tell how it ended.

        An alternative whose group (entity, alt_group) was bound already is answered REQ_CANCEL at
        once and never queued: that conversation ends with the Machine_Req_Ack.
        """
        assert conv.first is not None
        head, entries = conv.first.first, conv.first.messages[1:]
        problem = _malformed_request(head, entries)
        if problem:
            self.log.warning("Machine_Request from %s refused: %s", conv.peer, problem)
            await conv.send(message(Msg.MACHINE_REQ_ACK, ack_code=AckCode.BAD_MESSAGE, note=problem))
            return
        machines = [e.machine_id for e in entries]
        waiter: asyncio.Future[Outcome] = asyncio.get_running_loop().create_future()
        self._waiters[conv.id] = waiter  # before the step: the pass in it may already bind the request
        try:
            queued: store.Queued = await self.steps.submit(
                lambda s: s.queue_request(
                    head.entity_id, head.op_type, machines, head.priority, conv.peer, conv.id, head.alt_group
                )
            )
        except BaseException:
            self._waiters.pop(conv.id, None)
            raise
        if queued.ack_code != AckCode.ACK_OK:
            self._waiters.pop(conv.id, None)
            self.log.info(
                "request of entity %s for %s (%s)%s refused: %s %s",
                head.entity_id,
                head.op_type,
                " AND ".join(machines),
                _group(head),
                queued.ack_code,
                queued.note,
            )
            await conv.send(message(Msg.MACHINE_REQ_ACK, ack_code=queued.ack_code, note=queued.note))
            return
        self.log.info(
            "request %d of entity %s for %s (%s)%s queued",
            queued.request_key,
            head.entity_id,
            head.op_type,
            " AND ".join(machines),
            _group(head),
        )
        await conv.send(message(Msg.MACHINE_REQ_ACK, ack_code=AckCode.ACK_OK, request_key=queued.request_key))
        await self._tell(conv, await waiter)

    async def cancel_request(self, conv: Conversation) -> None:
        """CANCEL_RE: end one request (or an entity's) with REQ_CANCEL; REQ_KEY_U if nothing was waiting."""
        assert conv.first is not None
        m = conv.first.first
        if m.request_key is None and m.entity_id is None:
            await conv.send(
                message(
                    Msg.CANCEL_REQ_ACK,
                    ack_code=AckCode.BAD_MESSAGE,
                    note="Cancel_Request needs a request_key or an entity_id",
                )
            )
            return
        n = await self.steps.submit(lambda s: s.cancel(m.request_key, m.entity_id, m.by or conv.peer))
        what = f"request {m.request_key}" if m.request_key is not None else f"the requests of entity {m.entity_id}"
        self.log.info("cancel %s by %s: %d cancelled", what, m.by or conv.peer, n)
        await conv.send(
            message(
                Msg.CANCEL_REQ_ACK,
                ack_code=AckCode.ACK_OK if n else AckCode.REQ_KEY_U,
                cancelled=n,
                note=None if n else f"nothing waiting to cancel for {what}",
            )
        )

    async def unreserve(self, conv: Conversation) -> None:
        """UNRESERVE: free machines of an entity, then schedule them (in the same step)."""
        assert conv.first is not None
        m = conv.first.first
        freed = await self.steps.free(m.entity_id, m.machine_id)
        if freed:
            self.log.info("entity %s freed %s (by %s)", m.entity_id, ", ".join(freed), m.by or conv.peer)
            await conv.send(message(Msg.UNRESERVE_ME_ACK, ack_code=AckCode.ACK_OK, freed=len(freed)))
        else:
            await conv.send(
                message(
                    Msg.UNRESERVE_ME_ACK,
                    ack_code=AckCode.NOT_RESERVED,
                    freed=0,
                    note=f"{m.machine_id or 'no machine'} is not reserved by entity {m.entity_id}",
                )
            )

    async def update_me_status(self, conv: Conversation) -> None:
        """UPD_ME_ST (broadcast by the Machine Server): a machine went down, or came up."""
        assert conv.first is not None
        m = conv.first.first
        if m.status == MachineStatus.SHUTDOWN:
            n = await self.steps.submit(lambda s: s.machines_down())
            self.log.info("machine %s shut down: %d request(s) left the queue", m.machine_id, n)
        elif m.status in store.UP and m.previous not in store.UP:
            # Only a machine coming up may serve someone now: Idle, Setup and Running are all up, and a
            # move between them (three a run) changes nothing the pass looks at. What does change in a
            # run, its accept types and its reservation, comes as its own conversation and pass.
            await self.steps.submit(lambda s: s.machine_up(m.machine_id))

    async def accept_type_change(self, conv: Conversation) -> None:
        """ACC_TYP_C: what a machine accepts now; schedules when something was added (6.2.4.6)."""
        assert conv.first is not None
        m = conv.first.first
        if not all(isinstance(t, str) and t for t in m.op_types):
            await conv.send(
                message(Msg.CHG_ACCEPT_TYPE_ACK, ack_code=AckCode.BAD_MESSAGE, note="op_types must be a list of names")
            )
            return
        code, note = await self.steps.submit(lambda s: s.set_accept_types(m.machine_id, m.op_types))
        self.log.info("accept types of %s: %s %s", m.machine_id, code, note)
        await conv.send(message(Msg.CHG_ACCEPT_TYPE_ACK, ack_code=code, note=note))

    # ------------------------------------------------------------------ telling the entities

    def _dispatch(self, outcomes: list[Outcome]) -> None:
        for o in outcomes:
            if o.ack_code == AckCode.ACK_OK:
                self.log.info(
                    "request %d bound: entity %d gets %s, machine_run_id %d",
                    o.request_key,
                    o.entity_id,
                    ", ".join(o.machines),
                    o.machine_run_id,
                )
            else:
                self.log.info(
                    "request %d of entity %d ends %s (%s)", o.request_key, o.entity_id, o.ack_code, o.note or ""
                )
            self._acks[o.request_key] = asyncio.get_running_loop().create_future()
            waiter = self._waiters.pop(o.reply_conv or "", None)
            if waiter is not None and not waiter.done():
                waiter.set_result(o)  # its MACH_REQ task is still here: it tells
            elif o.reply_to and o.reply_conv:
                conv = self.bus.resume(o.reply_conv, Conv.MACH_REQ, o.reply_to)
                self.spawn(self._tell(conv, o))
            else:
                self.log.warning(
                    "request %d has no conversation to answer in: outcome %s not told", o.request_key, o.ack_code
                )
                self._told(o)

    async def _tell(self, conv: Conversation, o: Outcome) -> None:
        """Send the Machine_Req_Comp (and Reserved_Machine list) and wait, with a deadline, for its ack."""
        ok = o.ack_code == AckCode.ACK_OK
        msgs: list[Message] = [
            message(
                Msg.MACHINE_REQ_COMP,
                ack_code=o.ack_code,
                entity_id=o.entity_id,
                machine_run_id=o.machine_run_id,
                request_key=o.request_key,
                num_machines=len(o.machines) if ok else 0,
                note=o.note,
            )
        ]
        if ok:
            msgs += [message(Msg.RESERVED_MACHINE, machine_id=m) for m in o.machines]
        try:
            await conv.send(*msgs)
            answer = (await conv.next_message(self.ack_timeout)).first
            if answer.name != Msg.REQUEST_COMP_ACK:
                self.log.warning("request %d: expected Request_Comp_Ack, got %s", o.request_key, answer.name)
            elif answer.ack_code != AckCode.ACK_OK:
                self.log.warning(
                    "request %d: entity %d answered %s %s",
                    o.request_key,
                    o.entity_id,
                    answer.ack_code,
                    answer.note or "",
                )
        except GwcError as e:
            self.log.warning(
                "request %d: entity %d did not acknowledge its Machine_Req_Comp (%s)%s",
                o.request_key,
                o.entity_id,
                e,
                ": its machines stay reserved until it (or the Lot Server) frees them" if ok else "",
            )
        finally:
            conv.end()
        self._told(o)  # not when cancelled (MSCHED stopping): the next start tells it again

    def _told(self, o: Outcome) -> None:
        self.steps.forget(o.request_key)
        done = self._acks.pop(o.request_key, None)
        if done is not None and not done.done():
            done.set_result(None)


def _malformed_request(head: Message, entries: tuple[Message, ...]) -> str | None:
    """Why a Machine_Request batch does not make a request, or None."""
    if head.num_machines < 1:
        return "num_machines must be at least 1"
    if any(e.name != Msg.MACHINE_ENTRY for e in entries):
        return "only Machine_Entry messages may follow a Machine_Request"
    if len(entries) != head.num_machines:
        return f"num_machines is {head.num_machines} but {len(entries)} Machine_Entry followed"
    ids = [e.machine_id for e in entries]
    if len(set(ids)) != len(ids):
        return "a machine is named twice in one request"
    if not head.op_type:
        return "op_type is empty"
    if head.alt_group == "":
        return "alt_group is empty (leave it out for a request without alternatives)"
    return None


def _group(head: Message) -> str:
    """The request's alternative group, for the log."""
    return f" alt_group {head.alt_group}" if head.alt_group is not None else ""
