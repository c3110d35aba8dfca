"""The operation entity on the bus (BusLink): its conversations with the servers (asked again while a
server is away), the broadcasts it listens to and the interest it declares, the peers it watches
(see gwc/lot/entity.py)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Coroutine, Iterable
from typing import Any

from gwc.errors import ConversationTimeout
from gwc.ipc.bus import Batch, BlockingBus, BlockingConversation
from gwc.ipc.catalogue import Message
from gwc.lot.core import Heard
from gwc.lot.errors import LotError, LotTimeout
from gwc.lot.model import ABOUT_MACHINES, LISTENS, WAITING_LISTENS
from gwc.lot.state import EntityState
from gwc.module import ask_again


class BusLink:
    """The entity's bus: its conversations with servers (`ask`), the coroutines it runs on the bus's
    thread (`spawn`), and what it hears (`watch`, `listen_in_cell`) into its Heard."""

    def __init__(self, facts: EntityState, heard: Heard) -> None:
        self.facts = facts
        self.heard = heard
        self.blocking: BlockingBus | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        # The machines whose news (UPD_ME_ST, RUN_COMPL) the entity hears: bound to it and not given back.
        self._watching: set[str] = set()
        self._in_cell = False  # its lot is imported: it hears MOD_DIED

    def open(self) -> None:
        """Join the bus as lot:E and listen."""
        # A lot talks to servers and WCs, never to another lot: it does not track the other lot scripts
        # (their beats, hellos and byes are dropped before it wakes), nor answer their queries. It hears
        # the machines' news once it is in the cell (listen_in_cell).
        facts = self.facts
        self.blocking = BlockingBus(
            facts.name, facts.cfg.bus, facts.log, interest=WAITING_LISTENS, ignored_peers=("lot:",)
        )
        self.blocking.call_soon(self.heard.watch_peers, self.blocking.bus)
        self.blocking.peers()  # returns after watch_peers ran (the bus thread runs callbacks in order)
        self.spawn(self._listen())

    def close(self) -> None:
        """Leave the bus. Safe to call twice."""
        if self.blocking is None:
            return
        bus, self.blocking = self.blocking, None
        if self.heard.about:  # its own machines' only (docs/protocol.md, "Subjects")
            heard = ", ".join(f"{m} {n}" for m, n in sorted(self.heard.about.items()))
            self.facts.log.info("machine news heard (UPD_ME_ST, RUN_COMPL): %s", heard)
        bus.call_soon(self._cancel_tasks)
        with contextlib.suppress(Exception):
            bus.close()

    def need(self) -> BlockingBus:
        """The bus, or LotError if the entity is not open."""
        if self.blocking is None:
            raise LotError(f"entity {self.facts.entity_id} is not open")
        return self.blocking

    def present(self, name: str) -> bool:
        """Is `name` on the bus now (as this entity's bus last heard)?"""
        return self.heard.present(name)

    # ----------------------------------------------------------------- conversations

    def ask(
        self, cls: str, first: Message, to: str, timeout: float | None = None, within: float | None = None
    ) -> Message:
        """One conversation with a server (ls, msched, ms): its answer.

        A server away from the bus, unable to answer now (`ask_again`: not started as it restarts,
        or its database away) or silent past `timeout` is asked again, in a NEW conversation, after a
        pause (Timeouts.backoff, doubling to backoff_max) until `within` (Timeouts.retry) has passed;
        then LotTimeout. So every request sent through here must be safe to repeat (ENTITY_REQ,
        CANCEL_RE, UNRESERVE are).
        """
        self.need()
        return self._answer(cls, first, to, timeout, within, None)

    def ask_soon(
        self, cls: str, first: Message, to: str, timeout: float | None = None, within: float | None = None
    ) -> Callable[[], Message]:
        """ask's first try sent now; the function returned waits for its answer (asking again as ask
        does), so the script can work meanwhile. Call it: it also ends the conversation."""
        bus = self.need()
        sent = None
        if self.present(to):
            sent = bus.request_soon(cls, first, to=to, timeout=timeout or self.facts.timeouts.answer)
        return lambda: self._answer(cls, first, to, timeout, within, sent)

    def ask_once(self, cls: str, first: Message, to: str) -> Message:
        """One conversation, not asked again: its answer."""
        conv, batch = self.need().request(cls, first, to=to, timeout=self.facts.timeouts.answer)
        conv.end()
        return batch.first

    def _answer(
        self,
        cls: str,
        first: Message,
        to: str,
        timeout: float | None,
        within: float | None,
        sent: Callable[[], tuple[BlockingConversation, Batch]] | None,
    ) -> Message:
        bus, log, timeouts = self.need(), self.facts.log, self.facts.timeouts
        backoff = timeouts.asking(within)
        while True:
            error: ConversationTimeout | None = None
            if sent is None and not self.present(to):
                why = f"{to} is not on the bus"
            else:
                try:
                    if sent is not None:  # the first try, sent by ask_soon
                        answer, sent = sent, None
                        conv, batch = answer()
                    else:
                        conv, batch = bus.request(cls, first, to=to, timeout=timeout or timeouts.answer)
                except ConversationTimeout as e:
                    why, error = f"no answer within {timeout or timeouts.answer:.1f}s", e
                else:
                    conv.end()
                    if not ask_again(batch.first):
                        if backoff.tries:
                            log.info("%s answered %s after %d more tries", to, cls, backoff.tries)
                        return batch.first
                    why = f"{to} cannot answer now ({batch.first.ack_code} {batch.first.note or ''})"
            pause = backoff.next()
            if pause is None:
                log.error("%s to %s: %s; gave up after %d tries", cls, to, why, backoff.tries)
                raise LotTimeout(
                    f"entity {self.facts.entity_id}: {cls} to {to} failed: {why} (asked {backoff.tries} times)"
                ) from error
            log.warning("%s to %s: %s; asking again in %.1fs", cls, to, why, pause)
            time.sleep(pause)

    # ----------------------------------------------------------------- the bus's thread

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run a coroutine on the bus's event loop (its thread), kept so close() can cancel it."""
        bus = self.need()

        def launch() -> None:
            task = asyncio.get_running_loop().create_task(coro)
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        bus.call_soon(launch)

    def call_soon(self, fn: Callable[[], object]) -> None:
        """Run `fn` on the bus's thread (nothing if the entity is closed)."""
        if self.blocking is not None:
            self.blocking.call_soon(fn)

    def _cancel_tasks(self) -> None:
        for t in list(self._tasks):
            t.cancel()

    async def _listen(self) -> None:
        """Broadcasts this entity listens to (RUN_COMPL, UPD_ME_ST, MOD_DIED) and its own LOT_MOVED."""
        bus = self.need().bus
        while True:
            conv = await bus.first_message()
            if conv is None or conv.first is None:
                if bus.closed:
                    return
                continue
            conv.end()
            self.heard.hear(conv.first.first)

    # ----------------------------------------------------------------- interest

    def listen_in_cell(self) -> None:
        """From now on hear the cell's news (MOD_DIED): the lot is in the cell."""
        with self.heard.cond:
            if self._in_cell:
                return
            self._in_cell = True
        self._hear_now()

    def watch(self, machines: Iterable[str]) -> None:
        """Hear the news (UPD_ME_ST, RUN_COMPL) of these machines from now on: they are bound to the entity.
        Called at the binding, on the bus thread, so the filter is in place before any setup is sent."""
        with self.heard.cond:
            if self._watching.issuperset(machines):
                return
            self._watching.update(machines)
        self._hear_now()

    def unwatch(self, machine_id: str | None) -> None:
        """Stop hearing a machine's news (None: every machine's): it is given back. Not waited for: the
        script goes on while the bus thread applies it (a late Run_Complete it still hears is harmless)."""
        with self.heard.cond:
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
        if self.blocking is None:
            return
        if self.blocking.in_bus_thread():
            self._set_interest()
        elif wait:
            self.blocking.call(self._set_interest)
        else:
            self.blocking.call_soon(self._set_interest)

    def _set_interest(self) -> None:
        """(bus thread) The interest from the entity's state, read at this moment: calls from either
        thread leave the last state applied whatever their order."""
        blocking = self.blocking
        if blocking is None or blocking.bus.closed:
            return
        with self.heard.cond:
            classes = LISTENS if self._in_cell else WAITING_LISTENS
            machines = frozenset(self._watching)
        blocking.bus.set_interest(classes, subjects=dict.fromkeys(ABOUT_MACHINES, machines))
