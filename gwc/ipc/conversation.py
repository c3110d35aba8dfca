"""The conversation layer's parts: a conversation as one module sees it, the batches it delivers, the
peers it knows, and the small per-message records the bus keeps (see gwc/ipc/bus.py for the rules).

Plain __slots__ classes for the records: one is made per message, and a dataclass's generated
__init__ (default factories, keyword handling) costs more than the rest of the bookkeeping.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from gwc.config import BusConfig
from gwc.errors import BusError, ConversationTimeout, MessageError
from gwc.ipc.catalogue import Message

DEFAULT: Any = object()
INF = float("inf")
Names = tuple[str, ...]  # module names, or prefixes of them


@dataclass
class Peer:
    """A module seen on the bus: its name, its incarnation (a new one per process start), its interest."""

    name: str
    inc: int
    interest: frozenset[str]  # classes it hears whole
    last_seen: float
    subjects: dict[str, frozenset[str]] = field(default_factory=dict)  # class -> the only subjects it hears of it

    def hears(self, cls: str, subject: str) -> bool:
        """Whether it listens to broadcasts of `cls` about `subject` (docs/protocol.md, "Subjects")."""
        return cls in self.interest or (subject in self.subjects.get(cls, ()) if subject else False)


class Pending:
    """A msg datagram not yet acknowledged by every module it is meant for."""

    __slots__ = ("base", "batch", "cls", "conv", "data", "first_sent", "msg", "rto", "subject", "to", "waiting")

    def __init__(
        self,
        data: bytes,
        waiting: set[str],
        first_sent: float,
        rto: float,
        batch: list[int],
        conv: str,
        cls: str,
        msg: str,
        to: str | None,
        base: int,
        subject: str = "",
    ) -> None:
        self.data = data
        self.waiting = waiting
        self.first_sent = first_sent
        self.rto = rto
        self.batch = batch  # the Outgoing.unsettled entry [start_idx, datagrams not yet settled]
        self.conv = conv
        self.cls = cls
        self.msg = msg
        self.to = to
        self.base = base  # the base this datagram was encoded with
        self.subject = subject  # what a broadcast is about ("" if its class names no subject)


class Outgoing:
    """What this module sent in one conversation: the next idx, and its batches not yet settled.

    Outlives the Conversation object (bounded), so a conversation ended and later resumed in the same
    incarnation goes on numbering where it stopped, and its receivers can tell settled from missing.
    """

    __slots__ = ("next_idx", "unsettled")

    def __init__(self, next_idx: int = 0) -> None:
        self.next_idx = next_idx
        # None once all are settled: most of the remembered entries then hold no container for the garbage
        # collector to walk again and again. A list, oldest first: a conversation has a batch or two
        # unsettled at a time, and a list is made in a fraction of a deque's time.
        self.unsettled: list[list[int]] | None = None

    @property
    def base(self) -> int:
        return self.unsettled[0][0] if self.unsettled else self.next_idx


@dataclass(slots=True)
class Batch:
    """Messages delivered together: a first message and the `more` that followed it (a value: not
    frozen only because a frozen dataclass's __init__ costs several times a plain one's)."""

    sender: str
    messages: tuple[Message, ...]

    @property
    def first(self) -> Message:
        return self.messages[0]


CLOSED: Any = object()  # put in inboxes when the bus closes, so every waiter fails at once


class ConversationHost(Protocol):
    """What a Conversation needs from its bus (gwc.ipc.bus.Bus is one)."""

    cfg: BusConfig
    log: logging.Logger
    stats: collections.Counter[str]
    deadlines: Deadlines

    def send_batch(self, conv: Conversation, messages: tuple[Message, ...], to: str | None) -> int:
        """Number, encode, transmit and track one batch of the conversation; its next idx."""
        ...

    def end_conversation(self, conv: Conversation) -> None:
        """Route no more messages to the conversation."""
        ...


class Conversation:
    """One conversation as seen by one module: send into it, wait for the other side's messages."""

    __slots__ = ("_inbox", "_waiter", "bus", "cls", "ended", "first", "id", "initiator", "peer", "sent")

    def __init__(
        self, bus: ConversationHost, conv_id: str, cls: str, initiator: str, first: Batch | None = None
    ) -> None:
        self.bus = bus
        self.id = conv_id
        self.cls = cls
        self.initiator = initiator
        self.first = first  # for an incoming conversation: the batch that opened it
        self.peer: str | None = first.sender if first else None
        self._inbox: collections.deque[Batch] | None = None  # made when a batch comes before its wait
        self._waiter: asyncio.Future[Batch] | None = None
        self.sent = 0  # messages this module has sent in the conversation so far (its bus counts them)
        self.ended = False

    @property
    def incoming(self) -> bool:
        return self.first is not None

    def __repr__(self) -> str:
        return f"<Conversation {self.cls} {self.id}>"

    async def send(self, *messages: Message, to: str | None = DEFAULT) -> None:
        """Send a batch into this conversation; by default to the other side (or to all, if unknown)."""
        target = self.peer if to is DEFAULT else to
        self.sent = self.bus.send_batch(self, messages, target)

    def reply(self, *messages: Message) -> None:
        """send() to the other side, now, without a coroutine: for a handler that answers at once
        (Bus.accept)."""
        self.sent = self.bus.send_batch(self, messages, self.peer)

    async def next_message(self, timeout: float | None = None) -> Batch:
        """The next batch the other side sends; ConversationTimeout (logged) if none comes in time."""
        if self.ended:
            raise BusError(f"{self.cls} conversation {self.id} has ended")
        if self._inbox:
            batch = self._inbox.popleft()
        else:
            # A bare future whose deadline the bus keeps (no Queue, no wait_for task, no timer of its own:
            # this is the bus's hot path).
            bus = self.bus
            t = bus.cfg.reply_timeout if timeout is None else timeout
            waiter = self._waiter = bus.deadlines.waiter(t)
            try:
                batch = await waiter
            except TimeoutError:
                who = self.peer or f"any module listening to {self.cls}"
                err = ConversationTimeout(f"{self.cls} conversation {self.id}: no answer from {who} within {t:.1f}s")
                bus.stats["timeouts"] += 1
                bus.log.error("%s", err, extra={"conv": f"{self.id} {self.cls}"})
                raise err from None
            finally:
                bus.deadlines.discard(waiter)
                self._waiter = None
        if batch is CLOSED:
            if self._inbox is None:
                self._inbox = collections.deque()
            self._inbox.appendleft(batch)
            raise BusError(f"{self.cls} conversation {self.id}: the bus was closed while waiting")
        self.peer = batch.sender
        return batch

    def deliver(self, batch: Batch) -> None:
        """A batch (or CLOSED) for this conversation: to its waiter, or kept for the next next_message()."""
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(batch)
        elif self._inbox is None:
            self._inbox = collections.deque((batch,))
        else:
            self._inbox.append(batch)

    async def expect(self, *names: str, timeout: float | None = None) -> Batch:
        """next_message(), checked to be one of the named message classes."""
        batch = await self.next_message(timeout)
        if names and batch.first.name not in names:
            raise MessageError(
                f"{self.cls} {self.id}: expected {' or '.join(names)}, got {batch.first.name} from {batch.sender}"
            )
        return batch

    def end(self) -> None:
        """Stop routing messages to this conversation (late ones are acknowledged, logged and dropped)."""
        if not self.ended:
            self.ended = True
            self.bus.end_conversation(self)


def initiator(conv_id: str) -> str | None:
    """The module that opened a conversation, from its id '<initiator>.<inc hex>.<n>'."""
    parts = conv_id.rsplit(".", 2)
    return parts[0] if len(parts) == 3 else None


class Deadlines:
    """Every wait's deadline, kept by one timer armed for the earliest (not a timer per wait): a waiter
    fails with TimeoutError when its deadline passes unless it is done before."""

    def __init__(self) -> None:
        self.loop: asyncio.AbstractEventLoop | None = None  # set when the bus signs on
        self._at: dict[asyncio.Future[Any], float] = {}
        self._timer: asyncio.TimerHandle | None = None
        self._next = INF

    def waiter(self, timeout: float) -> asyncio.Future[Any]:
        assert self.loop is not None
        waiter = self.loop.create_future()
        deadline = time.monotonic() + timeout
        self._at[waiter] = deadline
        if deadline < self._next:
            if self._timer is not None:
                self._timer.cancel()
            self._next = deadline
            self._timer = self.loop.call_later(timeout, self._expire)
        return waiter

    def discard(self, waiter: asyncio.Future[Any]) -> None:
        self._at.pop(waiter, None)

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()

    def _expire(self) -> None:
        self._timer = None
        now = time.monotonic() + 0.001  # the loop may run a timer a hair early: do not re-arm for that
        nxt = INF
        for waiter, deadline in list(self._at.items()):
            if deadline <= now:
                del self._at[waiter]
                if not waiter.done():
                    waiter.set_exception(TimeoutError())
            elif deadline < nxt:
                nxt = deadline
        self._next = nxt
        if nxt < INF:
            assert self.loop is not None
            self._timer = self.loop.call_later(nxt - now, self._expire)
