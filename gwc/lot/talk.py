"""The operation entity on the bus: the conversations it holds (asked again while a server is away),
the broadcasts it listens to, the peers it watches, and its conversations with the Lot Server
(see gwc/lot/entity.py)."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable, Coroutine, Iterable, Sequence
from typing import Any

from gwc.errors import ConversationTimeout, GwcError
from gwc.ipc import Batch, BlockingConversation, Bus, Conversation, Peer
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.lot.core import EntityCore
from gwc.lot.errors import LotError, LotTimeout, MachineLost
from gwc.lot.model import (
    ABOUT_MACHINES,
    ALREADY,
    FOREVER,
    HISTORY,
    LISTENS,
    POLL,
    SHUT,
    WAITING_LISTENS,
    Alternative,
    S,
    WcCall,
)
from gwc.module import ask_again


class EntityTalk(EntityCore):
    """The entity's bus: conversations, broadcasts, peers; ENTITY_REQ to the Lot Server."""

    # ----------------------------------------------------------------- the Lot Server

    def entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
    ) -> Message:
        """ENTITY_REQ: ask the Lot Server to move this entity (import, export, completed, failed ...).

        Asked again while the Lot Server is away or not started (see `_ask`). Every action is safe to
        repeat: the Lot Server moves an entity only into the state it is asked for (attach, completed,
        failed, waiting_machine, running: a repeat finds it there and changes nothing), and a repeated
        import or export that finds the operator already moved the entity on is taken as done (ALREADY).
        Progress reports sent before (report()) are answered first; one that failed raises here.
        """
        self._drain_reports()
        return self._entity_request(action, reason, script_pid, timeout, within)

    def _attach(self) -> Message:
        """ENTITY_REQ attach: the Lot Server records our pid and answers with the entity's state, its lot
        and its lot script (the lot's own, else its product's; None if neither names one)."""
        try:
            ack = self.entity_request("attach", script_pid=os.getpid())
        except LotTimeout:
            raise
        except LotError:
            self._failed = True  # refused (unknown, failed or exported): nothing of ours to clean up
            raise
        self.product_id, self.priority, self.work_order_id = ack.product_id, ack.priority, ack.work_order_id
        self.script_id, self.script_path = ack.script_id, ack.script_path
        return ack

    def read_state(self) -> str | None:
        """The entity's state as the Lot Server has it, asked once (None if it has none for the entity or
        does not answer now): the fallback of a wait for a broadcast that may have been missed."""
        try:
            state = self._entity_request("state", within=0, keep_state=True).state
        except GwcError as e:
            self.log.warning("entity %d: state not read from the Lot Server: %s", self.entity_id, e)
            return None
        return None if state is None else str(state)

    def _wait_moved(self, action: str, states: Sequence[str], timeout: float) -> None:
        """Wait for LOT_MOVED(action) for this entity, asking the Lot Server for its state as a fallback
        every POLL seconds (not at every wake-up: every machine's news wakes a lot in the cell)."""
        deadline = time.monotonic() + timeout
        while True:
            next_poll = time.monotonic() + POLL
            with self._cond:
                while True:
                    for act, lot_id in self._moved:
                        if act == action:
                            if lot_id is not None:
                                self.lot_id = lot_id
                            return
                    left = min(next_poll, deadline) - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            state = self.read_state()
            if state in states:
                return
            if state == S.FAILED:
                raise LotError(f"entity {self.entity_id} was marked failed while waiting for {action}")
            if time.monotonic() > deadline:
                raise LotTimeout(
                    f"entity {self.entity_id}: the operator did not {action} the lot within "
                    f"{timeout:.0f}s (it is {state})"
                )

    def report(self, action: str) -> None:
        """ENTITY_REQ for a progress state (waiting_machine, running), sent without waiting for the answer.

        The Lot Server records progress for the operator; the operation does not need its answer, so
        reports go in the background, one at a time and in order (asked again while the Lot Server is
        away, as entity_request is), and the next entity_request waits for them first. A report the
        Lot Server refuses raises there, at the latest when the lot completes or fails.
        """
        self._set_state(action)
        if self._reporter is None:
            raise LotError(f"entity {self.entity_id} is not open")
        self._reports.append(self._reporter.submit(self._entity_request, action, keep_state=True))

    def _drain_reports(self) -> None:
        reports, self._reports = self._reports, []
        for report in reports:
            report.result()

    def _entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
        keep_state: bool = False,
    ) -> Message:
        ack = self._ask(
            Conv.ENTITY_REQ,
            message(Msg.ENTITY_REQUEST, entity_id=self.entity_id, action=action, reason=reason, script_pid=script_pid),
            "ls",
            timeout,
            within,
        )
        if ack.ack_code == AckCode.NOTNOW and ack.state in ALREADY.get(action, ()):
            self.log.info("entity %d: %s already done (the entity is %s)", self.entity_id, action, ack.state)
        elif ack.ack_code != AckCode.ACK_OK:
            raise LotError(
                f"the Lot Server refused {action} for entity {self.entity_id}: {ack.ack_code}"
                + (f" ({ack.note})" if ack.note else "")
                + (f", entity is {ack.state}" if ack.state else "")
            )
        if ack.lot_id is not None:
            self.lot_id = ack.lot_id
        if ack.state and not keep_state:  # a report's answer comes after the script has moved on
            self._set_state(ack.state)
        return ack

    def _listen_in_cell(self) -> None:
        """From now on hear the cell's news (MOD_DIED): the lot is in the cell."""
        with self._cond:
            if self._in_cell:
                return
            self._in_cell = True
        self._hear_now()

    def _watch(self, machines: Iterable[str]) -> None:
        """Hear the news (UPD_ME_ST, RUN_COMPL) of these machines from now on: they are bound to the entity.
        Called at the binding, on the bus thread, so the filter is in place before any setup is sent."""
        with self._cond:
            if self._watching.issuperset(machines):
                return
            self._watching.update(machines)
        self._hear_now()

    def _unwatch(self, machine_id: str | None) -> None:
        """Stop hearing a machine's news (None: every machine's): it is given back. Not waited for: the
        script goes on while the bus thread applies it (a late Run_Complete it still hears is harmless)."""
        with self._cond:
            if machine_id is None:
                if not self._watching:
                    return
                self._watching.clear()
            elif machine_id in self._watching:
                self._watching.discard(machine_id)
            else:
                return
        self._hear_now(wait=False)

    def _hear_now(self, wait: bool = True) -> None:
        """Apply the entity's interest as it is now, on the bus thread (returns once applied if `wait`)."""
        if self._bus is None:
            return
        if self._bus.in_bus_thread():
            self._set_interest()
        elif wait:
            self._bus.call(self._set_interest)
        else:
            self._bus.call_soon(self._set_interest)

    def _set_interest(self) -> None:
        """(bus thread) The interest from the entity's state, read at this moment: calls from either
        thread leave the last state applied whatever their order."""
        blocking = self._bus
        if blocking is None or blocking.bus.closed:
            return
        with self._cond:
            classes = LISTENS if self._in_cell else WAITING_LISTENS
            machines = frozenset(self._watching)
        blocking.bus.set_interest(classes, subjects=dict.fromkeys(ABOUT_MACHINES, machines))

    # ----------------------------------------------------------------- conversations

    def _present(self, name: str) -> bool:
        """Is `name` on the bus now (as this entity's bus last heard)?"""
        with self._cond:
            return name in self._peer_inc

    def _ask(
        self, cls: str, first: Message, to: str, timeout: float | None = None, within: float | None = None
    ) -> Message:
        """One conversation with a server (ls, msched): its answer.

        A server away from the bus, unable to answer now (`ask_again`: not started as it restarts,
        or its database away) or silent past `timeout` is asked again, in a NEW conversation, after a
        pause (Timeouts.backoff, doubling to backoff_max) until `within` (Timeouts.retry) has passed;
        then LotTimeout. So every request sent through here must be safe to repeat (ENTITY_REQ,
        CANCEL_RE, UNRESERVE are).
        """
        if self._bus is None:
            raise LotError(f"entity {self.entity_id} is not open")
        return self._answer(cls, first, to, timeout, within, None)

    def _ask_soon(
        self, cls: str, first: Message, to: str, timeout: float | None = None, within: float | None = None
    ) -> Callable[[], Message]:
        """_ask's first try sent now; the function returned waits for its answer (asking again as _ask
        does), so the script can work meanwhile. Call it: it also ends the conversation."""
        if self._bus is None:
            raise LotError(f"entity {self.entity_id} is not open")
        sent = None
        if self._present(to):
            sent = self._bus.request_soon(cls, first, to=to, timeout=timeout or self.timeouts.answer)
        return lambda: self._answer(cls, first, to, timeout, within, sent)

    def _answer(
        self,
        cls: str,
        first: Message,
        to: str,
        timeout: float | None,
        within: float | None,
        sent: Callable[[], tuple[BlockingConversation, Batch]] | None,
    ) -> Message:
        assert self._bus is not None
        backoff = self.timeouts.asking(within)
        while True:
            error: ConversationTimeout | None = None
            if sent is None and not self._present(to):
                why = f"{to} is not on the bus"
            else:
                try:
                    if sent is not None:  # the first try, sent by _ask_soon
                        answer, sent = sent, None
                        conv, batch = answer()
                    else:
                        conv, batch = self._bus.request(cls, first, to=to, timeout=timeout or self.timeouts.answer)
                except ConversationTimeout as e:
                    why, error = f"no answer within {timeout or self.timeouts.answer:.1f}s", e
                else:
                    conv.end()
                    if not ask_again(batch.first):
                        if backoff.tries:
                            self.log.info("%s answered %s after %d more tries", to, cls, backoff.tries)
                        return batch.first
                    why = f"{to} cannot answer now ({batch.first.ack_code} {batch.first.note or ''})"
            pause = backoff.next()
            if pause is None:
                self.log.error("%s to %s: %s; gave up after %d tries", cls, to, why, backoff.tries)
                raise LotTimeout(
                    f"entity {self.entity_id}: {cls} to {to} failed: {why} (asked {backoff.tries} times)"
                ) from error
            self.log.warning("%s to %s: %s; asking again in %.1fs", cls, to, why, pause)
            time.sleep(pause)

    def _ask_wc(self, cls: str, first: Message, machine_id: str, machine_run_id: int, timeout: float) -> Message:
        """One conversation with a machine's WC, given up (MachineLost) as soon as the machine is lost:
        it went Shutdown (UPD_ME_ST, or MACHINE_STATUS read meanwhile), or its WC left the bus for longer
        than lost_grace or came back as a new process (which knows nothing of this conversation) --
        rather than after the step's whole deadline. Never asked twice: a setup is not a repeatable step."""
        if self._bus is None:
            raise LotError(f"entity {self.entity_id} is not open")
        call = WcCall()
        self._spawn(self._converse(call, self._bus.bus, cls, first, f"wc:{machine_id}", timeout))

        def answered() -> bool:
            if call.done:
                return True
            why = self._lost(machine_id, machine_run_id)
            if why:
                self.log.error("%s of run %d: %s; not waiting for wc:%s's answer", cls, machine_run_id, why, machine_id)
                raise MachineLost(f"{why} ({cls} of run {machine_run_id})")
            return False

        try:
            self._wait(
                answered,
                timeout + 1,
                f"wc:{machine_id}'s answer to {cls}",
                poll=lambda: self._read_status([machine_id], SHUT, None),
            )
        except BaseException:
            self._abandon(call)
            raise
        if call.error is not None:
            self._raise_if_lost(machine_id, machine_run_id, None)
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
        with self._cond:
            call.answer, call.error, call.done = answer, error, True
            self._cond.notify_all()

    def _abandon(self, call: WcCall) -> None:
        """Stop a conversation nobody waits for any more (its task ends it)."""
        call.abandoned = True
        if self._bus is not None:
            self._bus.call_soon(lambda: call.task.cancel() if call.task is not None else None)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run a coroutine on the bus's event loop (its thread), kept so close() can cancel it."""
        assert self._bus is not None

        def launch() -> None:
            task = asyncio.get_running_loop().create_task(coro)
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        self._bus.call_soon(launch)

    def _cancel_tasks(self) -> None:
        for t in list(self._tasks):
            t.cancel()

    # ----------------------------------------------------------------- broadcasts and peers

    async def _listen(self) -> None:
        """Broadcasts this entity listens to (RUN_COMPL, UPD_ME_ST, MOD_DIED) and its own LOT_MOVED."""
        assert self._bus is not None
        bus = self._bus.bus
        while True:
            conv = await bus.first_message()
            if conv is None or conv.first is None:
                if bus.closed:
                    return
                continue
            conv.end()
            m = conv.first.first
            with self._cond:
                if m.name in (Msg.RUN_COMPLETE, Msg.UPDATE_ME_STATUS):
                    self._heard_about[str(m.machine_id)] += 1
                if m.name == Msg.RUN_COMPLETE and m.machine_run_id is not None:
                    key = (m.machine_id, int(m.machine_run_id))
                    self._runs[key] = m.ack_code
                    if key in self._began and _all_str(m.results):
                        self._heard_results[key] = m.results
                elif m.name == Msg.UPDATE_ME_STATUS:
                    self._note(m.machine_id, m.status, m.machine_run_id)
                elif m.name == Msg.MODULE_DIED:
                    deaths = self._deaths.setdefault(m.module, [])
                    deaths.append((time.monotonic(), m.how))
                    del deaths[:-HISTORY]
                elif m.name == Msg.LOT_MOVED and int(m.entity_id) == self.entity_id:
                    self._moved.append((m.action, m.lot_id))
                self._cond.notify_all()

    def _watch_peers(self, bus: Bus) -> None:
        """(bus thread) Keep who is on the bus, and since when a module left, for the steps that wait on one."""
        with self._cond:
            self._peer_inc.update({name: p.inc for name, p in bus.peers().items()})
        bus.peer_listeners.append(self._peer_changed)

    def _peer_changed(self, name: str, peer: Peer | None) -> None:
        with self._cond:
            if peer is None:
                self._peer_inc.pop(name, None)
                self._peer_left[name] = time.monotonic()
            else:
                if name not in self._peer_inc and name.startswith("wc:"):
                    self._first_heard(name[3:], peer.inc)
                self._peer_inc[name] = peer.inc
            self._cond.notify_all()

    def _first_heard(self, machine_id: str, inc: int) -> None:
        """(under the lock) A WC heard of for the first time (WCs leave a lot's query at sign-on to their
        beat: gwc/wc/wc.py): runs begun on its machine before are its, so that from now on a restart of
        that WC (a new incarnation) tells the run is lost to it, as for a WC known when the run began."""
        for key, (when, known) in list(self._began.items()):
            if key[0] == machine_id and known is None:
                self._began[key] = (when, inc)

    # ----------------------------------------------------------------- MACH_REQ

    async def _request(self, alt: Alternative, priority: int | None) -> None:
        """One MACH_REQ conversation, from Machine_Request to its one Machine_Req_Comp.

        Until MSCHED takes it (Machine_Req_Ack), a MSCHED away, not started or silent is asked again
        in a new conversation, as `_ask` does: a request that did reach it and is asked again is one
        more alternative of the same alt_group, which MSCHED refuses once one is bound, and which the
        entity cancels once it has its machines.
        """
        assert self._bus is not None
        bus = self._bus.bus
        group = alt.group
        conv: Conversation | None = None
        backoff = self.timeouts.asking()
        try:
            while alt.ack is None and not alt.done:
                if group is not None and group.winner is not None:  # no need to ask any more
                    with self._cond:
                        alt.done = True
                        self._cond.notify_all()
                    return
                if not self._present("msched"):
                    why = "msched is not on the bus"
                else:
                    conv = await bus.start(
                        Conv.MACH_REQ,
                        message(
                            Msg.MACHINE_REQUEST,
                            entity_id=self.entity_id,
                            op_type=alt.op_type,
                            num_machines=len(alt.machines),
                            priority=priority,
                            alt_group=group.alt_group if group else None,
                        ),
                        *[message(Msg.MACHINE_ENTRY, machine_id=m) for m in alt.machines],
                        to="msched",
                    )
                    try:
                        batch = await conv.next_message(self.timeouts.answer)
                    except ConversationTimeout:
                        why = f"no answer within {self.timeouts.answer:.1f}s"
                    else:
                        if not ask_again(batch.first):
                            await self._answered(alt, conv, batch)
                            continue
                        why = f"msched cannot answer now ({batch.first.ack_code} {batch.first.note or ''})"
                    conv.end()
                    conv = None
                pause = backoff.next()
                if pause is None:
                    raise LotTimeout(
                        f"MACH_REQ for {alt.op_type} ({alt.describe()}): {why} (asked {backoff.tries} times)"
                    )
                self.log.warning(
                    "MACH_REQ for %s (%s): %s; asking again in %.1fs", alt.op_type, alt.describe(), why, pause
                )
                await asyncio.sleep(pause)
            while not alt.done:
                assert conv is not None
                await self._answered(alt, conv, await conv.next_message(FOREVER))
        except asyncio.CancelledError:
            raise
        except (GwcError, OSError) as e:
            with self._cond:
                alt.error = str(e)
                alt.done = True
                self._cond.notify_all()
        finally:
            if conv is not None:
                conv.end()

    async def _answered(self, alt: Alternative, conv: Conversation, batch: Batch) -> None:
        """MSCHED's Machine_Req_Ack or Machine_Req_Comp for one alternative."""
        head = batch.first
        if head.name == Msg.MACHINE_REQ_COMP:
            await conv.send(message(Msg.REQUEST_COMP_ACK, entity_id=self.entity_id, ack_code=AckCode.ACK_OK))
        with self._cond:
            if head.name == Msg.MACHINE_REQ_ACK:
                alt.ack = head
                alt.done = head.ack_code != AckCode.ACK_OK
            elif head.name == Msg.MACHINE_REQ_COMP:
                alt.comp = head
                alt.reserved = [m.machine_id for m in batch.messages[1:] if m.name == Msg.RESERVED_MACHINE]
                alt.done = True
            taken = alt.group is not None and alt.group.winner not in (None, alt) and head.ack_code == AckCode.ACK_OK
            surplus = alt.group.surplus(alt) if taken and alt.group and head.name == Msg.MACHINE_REQ_COMP else []
            queued = taken and head.name == Msg.MACHINE_REQ_ACK
            self._cond.notify_all()
        if head.name == Msg.MACHINE_REQ_COMP and head.ack_code == AckCode.ACK_OK:
            # In this same turn of the bus's loop: whatever the script sends to the machines once woken is
            # sent after it, so no news of a machine it sets up can come before its filter hears them.
            self._watch([m.machine_id for m in batch.messages[1:] if m.name == Msg.RESERVED_MACHINE])
        for m in surplus:  # bound after the entity took another alternative: give it back
            self.log.warning("%s was bound after another alternative was taken: giving it back", m)
            self._unwatch(m)
            await self._tell(
                Conv.UNRESERVE, message(Msg.UNRESERVE_ME, entity_id=self.entity_id, machine_id=m, by=self.name)
            )
        if queued:  # queued after the entity took another alternative: it must not wait there
            self.log.warning("request %s was queued after another alternative was taken: cancelling it", alt.key)
            await self._tell(Conv.CANCEL_RE, message(Msg.CANCEL_REQUEST, request_key=alt.key, by=self.name))

    async def _tell(self, cls: str, first: Message) -> None:
        """(bus thread) A cleanup conversation with MSCHED whose answer only goes to the log."""
        assert self._bus is not None
        try:
            conv, batch = await self._bus.bus.request(cls, first, to="msched", timeout=self.timeouts.answer)
            conv.end()
            self.log.info("%s: %s", cls, batch.first.ack_code)
        except GwcError as e:
            self.log.error("%s failed: %s", cls, e)


def _all_str(results: Any) -> bool:
    """Whether a Run_Complete's results are what a WC sends (param -> value, all text); else they are read
    from MACHINE_RUN_RESULT."""
    return isinstance(results, dict) and all(isinstance(p, str) and isinstance(v, str) for p, v in results.items())
