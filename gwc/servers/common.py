"""What the five cell servers share: answering with an ack code, broadcasting, raising alarms.

Each server is a Module (gwc/module.py) and keeps the one lifecycle; this adds the few habits
every server has: a refusal is logged with its reason and answered with its ack code, a change
others must hear of is broadcast as its own one-message conversation, and an alarm goes to the
Cell Alarm Server without ever holding up the conversation that found it.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine
from typing import Any

from gwc import db
from gwc.config import Config, RecordConfig
from gwc.errors import GwcError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S

SERVER_TIMEOUT = 5.0  # longest one server waits for another's answer
# The servers no lot script talks to (CAS, ERS, SLS) do not track lot scripts (Module.ignored_peers): a
# lot may open only the catalogue's LOT_CLASSES, none of theirs, and none of them starts a class a lot
# listens to. Each lot's sign-on, change of interest at import and bye no longer wake them.
NOT_LOTS = ("lot:",)


class Server:
    """Mixin for a Module: the helpers above. Put it first in the bases: `class X(Server, Module)`."""

    name: str
    log: logging.Logger
    cfg: Config
    bus: Any
    _tasks: set[asyncio.Task[Any]]
    ask: Callable[..., Coroutine[Any, Any, Message]]

    @staticmethod
    def request(conv: Conversation) -> Message:
        """The message that opened an incoming conversation."""
        assert conv.first is not None
        return conv.first.first

    async def answer(
        self, conv: Conversation, name: str, code: str = AckCode.ACK_OK, note: str | None = None, **fields: Any
    ) -> None:
        """Answer a conversation; a refusal (any code but ACK_OK) is logged with its reason first."""
        if code != AckCode.ACK_OK:
            self.log.info("refused %s from %s: %s (%s)", conv.cls, conv.peer, code, note or "-")
        await conv.send(message(name, ack_code=code, note=note[:500] if note else None, **fields))

    async def broadcast(self, cls: str, msg: Message) -> None:
        """Tell every module listening to `cls` (a one-message conversation nobody answers)."""
        conv = await self.bus.start(cls, msg)
        conv.end()

    async def event(self, text: str) -> None:
        """A cell event for the status line (7.4)."""
        await self.broadcast(Conv.CELL_EVENT, message(Msg.CELL_EVENT, text=text[:500], source=self.name))

    def spawn(self, coro: Coroutine[Any, Any, object]) -> None:
        """Run work in the background, owned by the module (cancelled when it stops); its result is dropped."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def raise_alarm(self, alarm_id: str, text: str, machine_id: str | None = None) -> int | None:
        """Send an alarm to the CAS (ALARM_SEND); its alarm_no, or None (logged) if it was not taken.

        A CAS restarting or without its database is asked again for up to DATABASE_OUTAGE_S (call
        this in the background: `spawn`)."""
        try:
            ack = await self.ask(
                Conv.ALARM_SEND,
                message(
                    Msg.ALARM_SEND, alarm_id=alarm_id, alarm_text=text[:500], machine_id=machine_id, raised_by=self.name
                ),
                "cas",
                SERVER_TIMEOUT,
                within=DATABASE_OUTAGE_S,
            )
        except GwcError as e:  # ConversationTimeout among them
            self.log.error("alarm %s (%s) not taken by the Cell Alarm Server: %s", alarm_id, text, e)
            return None
        if ack.ack_code != AckCode.ACK_OK:
            self.log.error("Cell Alarm Server refused alarm %s: %s %s", alarm_id, ack.ack_code, ack.note or "")
            return None
        self.log.info("alarm %s raised as number %s", alarm_id, ack.alarm_no)
        return int(ack.alarm_no) if ack.alarm_no is not None else None

    def refusal(self, cls: str, req: Message, code: str, note: str) -> Message | None:
        """The refusal of a class whose answer needs more than an ack code (override per server)."""
        return None

    async def _refuse(self, conv: Conversation, code: str, note: str, **fields: Any) -> None:
        # Module._refuse answers only classes whose answer needs nothing but ack_code; a server's
        # other answers (Status_Reply, Status_Line) are built by refusal() so no client is left to
        # time out when, say, the database fails.
        if conv.sent or conv.first is None:
            return
        reply = self.refusal(conv.cls, conv.first.first, code, note)
        if reply is None:
            await super()._refuse(conv, code, note, **fields)  # type: ignore[misc]
            return
        try:
            await conv.send(reply)
        except GwcError as e:
            self.log.warning("could not refuse %s: %s", conv.cls, e)


class Pruner:
    """The production record's retention for one owner of history tables (docs/record.md, Retention):
    `prune_record(owner, keep_days)` at the module's first idle, then every `prune_every_s`. A failure
    is logged and tried again at the next turn."""

    def __init__(
        self,
        owner: str,
        what: str,
        record: RecordConfig,
        transaction: Callable[[db.Statement], Any],
        log: logging.Logger,
    ) -> None:
        self.owner, self.what, self.record = owner, what, record
        self.transaction, self.log = transaction, log
        self.last = 0.0  # monotonic time of the last prune (0: none yet)

    def on_idle(self, now: float) -> None:
        if not self.record.history or (self.last and now - self.last <= self.record.prune_every_s):
            return
        self.last = now
        days = self.record.keep_days
        try:
            row = self.transaction(db.Statement("select prune_record(%s, %s)", (self.owner, days)))
        except GwcError as e:
            self.log.error("pruning the %s failed: %s", self.what, e)
            return
        if row and row[0]:
            self.log.info("pruned %d rows of %s older than %g days", row[0], self.what, days)
