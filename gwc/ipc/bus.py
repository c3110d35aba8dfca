"""The CELL bus: reliable conversations over UDP multicast (the successor of the thesis's ISIS bus).

Every module joins one multicast group. A conversation is started by one module and broadcast to
every module interested in its class (or addressed to one module); answers travel in the same
conversation, addressed to the other side. On top of lossy UDP the bus gives:

* reliability: every msg datagram is acknowledged by each module it is meant for (acks are gathered
  per peer, or ride on the next msg to it); unacknowledged datagrams are retransmitted (exponential
  backoff) until acked or `retry_deadline` passes;
* exactly-once delivery: duplicates are recognised by (sender, incarnation, seq), re-acked, not
  delivered again, so a repeated request never causes a second action;
* order: each sender's messages in a conversation are delivered in the order sent; a batch (a first
  message saying `more` follow, e.g. Machine_Request + N x Machine_Entry) is delivered whole; each
  message's `base` says what before it is settled, so a receiver that restarted, or a conversation
  resumed long after, finds its place (see docs/protocol.md);
* late answers: a msg for a conversation this module ended is acknowledged, logged and dropped;
* membership: modules announce themselves (hello) every `heartbeat`, answer a newcomer's query at
  once, say bye on a clean close, and are dropped after `peer_timeout` of silence;
* no collisions: the bus is one asyncio event loop; receiving, acknowledging and retransmitting
  never wait for the application, and waiting for an answer never stops other conversations from
  arriving (thesis 8.2's deadlock, patched there with sleeps, cannot happen: see docs/protocol.md).

`Bus` is the asyncio API the modules use; `BlockingBus` runs one in a thread for plain scripts
(lot scripts, the Human Interface, tests) without a second implementation of anything.
"""

from __future__ import annotations

import asyncio
import collections
import ctypes
import heapq
import logging
import random
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterable
from dataclasses import dataclass, replace
from typing import Any, TypeVar

from gwc.config import BusConfig
from gwc.errors import BusError, ConversationTimeout, MessageError
from gwc.ipc import catalogue, wire
from gwc.ipc.catalogue import Message
from gwc.ipc.wire import Envelope
from gwc.log import TRACE

T = TypeVar("T")
_DEFAULT: Any = object()
RCVBUF = 4 * 1024 * 1024
IP_MULTICAST_ALL = 49  # Linux's value, for Pythons whose socket module does not name it
SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)  # Linux's value
MAX_RTO = 0.5  # retransmission backoff stops growing here
MAX_PIGGYBACK = 32  # acks riding on a msg at most; the rest go in ack datagrams
MAX_GONE = 1024  # incarnations that said bye, remembered so that their late beats are ignored
MAX_REMEMBERED = 65_536  # ended conversations (and our idx counters) remembered, newest first
INF = float("inf")


def open_socket(cfg: BusConfig, port: int | None = None) -> socket.socket:
    """A UDP socket joined to the cell's group on its interface, at `port` (the bus's, unless given);
    closed again if any step fails."""
    port = cfg.port if port is None else port
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
        sock.bind(("", port))
        iface = socket.inet_aton(cfg.interface)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(cfg.group) + iface)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, iface)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("b", 1))
        if sys.platform.startswith("linux"):
            # Only the groups this socket joined: without it Linux hands us every group joined on the
            # host at this port, and two cells on one port but different groups would hear each other.
            sock.setsockopt(socket.IPPROTO_IP, getattr(socket, "IP_MULTICAST_ALL", IP_MULTICAST_ALL), 0)
        sock.setblocking(False)
    except OSError as e:
        sock.close()
        raise BusError(f"cannot join bus group {cfg.group}:{port} on {cfg.interface}: {e}") from e
    return sock


@dataclass
class Peer:
    """A module seen on the bus: its name, its incarnation (a new one per process start), its interest."""

    name: str
    inc: int
    interest: frozenset[str]
    last_seen: float


class _Pending:
    """A msg datagram not yet acknowledged by every module it is meant for.

    Plain __slots__ classes here and below: one is made per message, and a dataclass's generated
    __init__ (default factories, keyword handling) costs more than the rest of the bookkeeping.
    """

    __slots__ = ("base", "batch", "cls", "conv", "data", "first_sent", "msg", "rto", "to", "waiting")

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
    ) -> None:
        self.data = data
        self.waiting = waiting
        self.first_sent = first_sent
        self.rto = rto
        self.batch = batch  # the _Outgoing.unsettled entry [start_idx, datagrams not yet settled]
        self.conv = conv
        self.cls = cls
        self.msg = msg
        self.to = to
        self.base = base  # the base this datagram was encoded with


class _Outgoing:
    """What this module sent in one conversation: the next idx, and its batches not yet settled.

    Outlives the Conversation object (bounded), so a conversation ended and later resumed in the same
    incarnation goes on numbering where it stopped, and its receivers can tell settled from missing.
    """

    __slots__ = ("next_idx", "unsettled")

    def __init__(self, next_idx: int = 0) -> None:
        self.next_idx = next_idx
        # None once all are settled: most of the remembered entries then hold no container for the garbage
        # collector to walk again and again.
        self.unsettled: collections.deque[list[int]] | None = None

    @property
    def base(self) -> int:
        return self.unsettled[0][0] if self.unsettled else self.next_idx


class _Stream:
    """Per (conversation, sender, incarnation): reorder buffer and the batch being assembled."""

    __slots__ = ("batch", "buffer", "gap_since", "next_idx", "touched")

    def __init__(self, next_idx: int, touched: float) -> None:
        self.next_idx = next_idx
        self.buffer: dict[int, tuple[Envelope, Message | None]] = {}
        self.batch: list[tuple[Envelope, Message | None]] | None = None  # made when a batch of several begins
        self.touched = touched
        self.gap_since = 0.0  # when the buffer last became non-empty (a message is missing)


class _Seen:
    """The seqs taken from one (sender, incarnation), for dedup: two generations, swapped every
    2 x retry_deadline by the housekeeping, so each seq is remembered that long at least (and at
    most twice that) for the price of two set lookups per msg."""

    __slots__ = ("new", "old", "since")

    def __init__(self, since: float) -> None:
        self.new: set[int] = set()
        self.old: set[int] = set()
        self.since = since


@dataclass(frozen=True)
class Batch:
    """Messages delivered together: a first message and the `more` that followed it."""

    sender: str
    messages: tuple[Message, ...]

    @property
    def first(self) -> Message:
        return self.messages[0]


_CLOSED: Any = object()  # put in inboxes when the bus closes, so every waiter fails at once


class Conversation:
    """One conversation as seen by one module: send into it, wait for the other side's messages."""

    def __init__(self, bus: Bus, conv_id: str, cls: str, initiator: str, first: Batch | None = None) -> None:
        self.bus = bus
        self.id = conv_id
        self.cls = cls
        self.initiator = initiator
        self.first = first  # for an incoming conversation: the batch that opened it
        self.peer: str | None = first.sender if first else None
        self._inbox: collections.deque[Batch] = collections.deque()
        self._waiter: asyncio.Future[Batch] | None = None
        self._idx = 0  # messages this module has sent in the conversation so far
        self.ended = False

    @property
    def incoming(self) -> bool:
        return self.first is not None

    def __repr__(self) -> str:
        return f"<Conversation {self.cls} {self.id}>"

    async def send(self, *messages: Message, to: str | None = _DEFAULT) -> None:
        """Send a batch into this conversation; by default to the other side (or to all, if unknown)."""
        target = self.peer if to is _DEFAULT else to
        self._idx = self.bus._send_batch(self, messages, target)

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
            waiter = self._waiter = bus._waiter(t)
            try:
                batch = await waiter
            except TimeoutError:
                who = self.peer or f"any module listening to {self.cls}"
                err = ConversationTimeout(f"{self.cls} conversation {self.id}: no answer from {who} within {t:.1f}s")
                bus.stats["timeouts"] += 1
                bus.log.error("%s", err, extra={"conv": f"{self.id} {self.cls}"})
                raise err from None
            finally:
                bus._deadlines.pop(waiter, None)
                self._waiter = None
        if batch is _CLOSED:
            self._inbox.appendleft(batch)
            raise BusError(f"{self.cls} conversation {self.id}: the bus was closed while waiting")
        self.peer = batch.sender
        return batch

    def _put(self, batch: Batch) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(batch)
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
            self.bus._end(self)


class Bus:
    """One module's attachment to the CELL bus (see the module docstring)."""

    def __init__(
        self,
        name: str,
        cfg: BusConfig,
        log: logging.Logger,
        interest: Iterable[str] = (),
    ) -> None:
        if not name or len(name) > wire.MAX_NAME - 30:
            raise BusError(f"bad bus module name {name!r}")
        self.name = name
        self.cfg = cfg
        self.log = log
        self.inc = random.SystemRandom().randrange(1, 2**31)
        self._interest: set[str] = set()
        self._kernel_filter = cfg.kernel_filter
        self._sock: socket.socket | None = None
        self.set_interest(interest, announce=False)
        self._seq = 0
        self._conv_n = 0
        self._dest = (cfg.group, cfg.port)
        self._buf = bytearray(65_536)  # one receive buffer, reused: no 256 KiB allocation per datagram
        self._view = memoryview(self._buf)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._peers: dict[str, Peer] = {}
        self._pending: dict[int, _Pending] = {}
        # Retransmission: one timer for all pending msgs. First sends are due in send order (a deque);
        # retransmissions, with their backoff, in a heap. Entries of msgs acked since are skipped.
        self._due_first: collections.deque[tuple[float, int]] = collections.deque()
        self._due_again: list[tuple[float, int]] = []
        self._rtx_timer: asyncio.TimerHandle | None = None
        self._rtx_at = INF
        self._out: collections.OrderedDict[str, _Outgoing] = collections.OrderedDict()
        self._seen: dict[tuple[str, int], _Seen] = {}
        # Oldest-touched first, so housekeeping looks only at streams old enough to forget.
        self._streams: collections.OrderedDict[tuple[str, str, int], _Stream] = collections.OrderedDict()
        self._gaps: dict[tuple[str, str, int], _Stream] = {}  # streams holding messages that came early
        self._convs: dict[str, Conversation] = {}
        self._ended: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._acks_due: dict[tuple[str, int], list[int]] = {}
        self._ack_timer: asyncio.TimerHandle | None = None
        # New conversations, and the first_message() calls waiting for one (no asyncio.Queue: hot path).
        self._incoming: collections.deque[Conversation] = collections.deque()
        self._incoming_waiters: collections.deque[asyncio.Future[Conversation]] = collections.deque()
        # Every wait's deadline, kept by one timer armed for the earliest (not a timer per wait).
        self._deadlines: dict[asyncio.Future[Any], float] = {}
        self._deadline_timer: asyncio.TimerHandle | None = None
        self._deadline_at = INF
        self._heartbeat: asyncio.Task[None] | None = None
        # Periodic hellos (beats) travel on a port of their own, read only at each heartbeat: hearing
        # that every module is still there must not wake every module every few milliseconds.
        self._beat_sock: socket.socket | None = None
        self._beat_dest = (cfg.group, cfg.beat_port)
        self._beats: dict[bytes, tuple[str, int]] = {}  # each peer's last beat, as sent -> (name, inc)
        # Incarnations that said bye, newest last: a beat they sent before it, read after, is stale.
        self._gone: collections.OrderedDict[tuple[str, int], None] = collections.OrderedDict()
        self._faults = cfg.faults
        seed = cfg.faults.seed
        self._rng = random.Random(None if seed is None else f"{seed}:{name}")
        self._held: bytes | None = None
        self._origin = wire.origin(name, self.inc)
        self._mine = f"{name}."  # how the ids of conversations this module opened begin
        self._conv_prefix = f"{name}.{self.inc:x}."  # ... in this incarnation
        self._flushed: asyncio.Future[None] | None = None  # close() waiting for the last acks
        self.peer_listeners: list[Callable[[str, Peer | None], None]] = []
        self.stats = collections.Counter[str]()
        self.closed = False

    # ----------------------------------------------------------------- lifecycle

    async def sign_on(self, settle: float = 0.05) -> None:
        """Join the group, announce ourselves, and give present modules `settle` s to answer."""
        self._loop = asyncio.get_running_loop()
        self._sock = open_socket(self.cfg)
        self._filter()
        try:
            self._beat_sock = open_socket(self.cfg, self.cfg.beat_port)
        except BusError:
            self._sock.close()
            self._sock = None
            raise
        self._loop.add_reader(self._sock.fileno(), self._readable)
        self._hello(query=True)
        self._heartbeat = self._loop.create_task(self._beat())
        self.log.info("signed on to bus %s as %s (incarnation %x)", self.cfg.name, self.name, self.inc)
        if settle:
            await asyncio.sleep(settle)

    async def close(self, flush: float = 1.0) -> None:
        """Wait up to `flush` s for outstanding acks, say bye, leave; every waiter fails. Safe to call twice."""
        if self.closed:
            return
        self.closed = True
        self._flush_acks()
        if flush and self._pending and self._loop is not None:
            self._flushed = self._loop.create_future()
            try:
                await asyncio.wait_for(self._flushed, flush)
            except TimeoutError:
                self.log.warning("closing with %d datagram(s) unacknowledged", len(self._pending))
        for timer in (self._heartbeat, self._ack_timer, self._rtx_timer, self._deadline_timer):
            if timer is not None:
                timer.cancel()
        self._pending.clear()
        if self._sock is not None:
            self._raw_send(Envelope(kind="bye", src=self.name, inc=self.inc))
            if self._loop is not None:
                self._loop.remove_reader(self._sock.fileno())
            self._sock.close()
            self._sock = None
        if self._beat_sock is not None:
            self._beat_sock.close()
            self._beat_sock = None
        for conv in self._convs.values():
            conv._put(_CLOSED)
        self._put_incoming(_CLOSED)
        self.log.info("signed off bus %s", self.cfg.name)

    # ----------------------------------------------------------------- interest filters

    @property
    def interests(self) -> frozenset[str]:
        return frozenset(self._interest)

    def set_interest(self, classes: Iterable[str], announce: bool = True) -> None:
        """Listen to exactly these conversation classes from now on (thesis: interest/no_interest)."""
        new = set(classes)
        unknown = new - set(catalogue.CONVERSATION_CLASSES)
        if unknown:
            raise MessageError(f"unknown conversation class(es): {', '.join(sorted(unknown))}")
        self._interest = new
        if self._sock is not None:
            self._filter()
            if announce:
                self._hello()

    def _filter(self) -> None:
        """Have the kernel drop what this module would drop unread (wire.kernel_filter), where it can."""
        if not self._kernel_filter or self._sock is None:
            return
        code = wire.kernel_filter(self.name, self.inc, self._interest)
        program = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *c) for c in code))
        try:  # struct sock_fprog {unsigned short len; struct sock_filter *filter;}: the kernel copies the program
            self._sock.setsockopt(
                socket.SOL_SOCKET, SO_ATTACH_FILTER, struct.pack("HP", len(code), ctypes.addressof(program))
            )
        except OSError as e:  # not Linux, or filters forbidden: the bus drops the same datagrams itself
            self.log.warning("no kernel filter on the bus socket (%s): every datagram wakes this module", e)
            self._kernel_filter = False

    def interest(self, *classes: str) -> None:
        self.set_interest(self._interest | set(classes))

    def no_interest(self, *classes: str) -> None:
        self.set_interest(self._interest - set(classes))

    def peers(self) -> dict[str, Peer]:
        return dict(self._peers)

    def listeners_of(self, cls: str) -> list[str]:
        return sorted(p.name for p in self._peers.values() if cls in p.interest)

    # ----------------------------------------------------------------- conversations

    def _new_conv_id(self) -> str:
        self._conv_n += 1
        return f"{self._conv_prefix}{self._conv_n}"

    async def start(self, cls: str, *messages: Message, to: str | None = None) -> Conversation:
        """Open a conversation and send its first batch (broadcast to listeners of cls, or to one module)."""
        if cls not in catalogue.CONVERSATION_CLASSES:
            raise MessageError(f"unknown conversation class {cls!r}")
        conv = Conversation(self, self._new_conv_id(), cls, self.name)
        conv.peer = to
        self._convs[conv.id] = conv
        try:
            conv._idx = self._send_batch(conv, messages, to)  # conv.send() without its coroutine
        except BaseException:
            conv.end()
            raise
        return conv

    async def request(
        self, cls: str, *messages: Message, to: str | None = None, timeout: float | None = None
    ) -> tuple[Conversation, Batch]:
        """Open a conversation and wait for the first answer."""
        conv = await self.start(cls, *messages, to=to)
        try:
            return conv, await conv.next_message(timeout)
        except BaseException:
            conv.end()
            raise

    def resume(self, conv_id: str, cls: str, peer: str) -> Conversation:
        """Reopen a conversation known from elsewhere (the database) to answer in it after a restart."""
        if cls not in catalogue.CONVERSATION_CLASSES:
            raise MessageError(f"unknown conversation class {cls!r}")
        conv = self._convs.get(conv_id)
        if conv is None:
            conv = Conversation(self, conv_id, cls, _initiator(conv_id) or peer)
            conv.peer = peer
            out = self._out.get(conv_id)
            conv._idx = out.next_idx if out else 0
            self._convs[conv_id] = conv
            self._ended.pop(conv_id, None)
        return conv

    async def first_message(self, timeout: float | None = None) -> Conversation | None:
        """The next conversation another module opened with us; None after timeout (or once closed)."""
        if self.closed:
            return None
        if self._incoming:
            conv = self._incoming.popleft()
        else:
            waiter: asyncio.Future[Conversation]
            if timeout is None:
                assert self._loop is not None
                waiter = self._loop.create_future()
            else:
                waiter = self._waiter(timeout)
            self._incoming_waiters.append(waiter)
            try:
                conv = await waiter
            except TimeoutError:
                return None
            finally:
                self._deadlines.pop(waiter, None)
        if conv is _CLOSED:
            self._incoming.appendleft(conv)
            return None
        return conv

    def _put_incoming(self, conv: Conversation) -> None:
        """A new conversation: to the longest-waiting first_message() still waiting, or queued."""
        waiters = self._incoming_waiters
        while waiters:
            waiter = waiters.popleft()
            if not waiter.done():
                waiter.set_result(conv)
                return
        self._incoming.append(conv)

    def _waiter(self, timeout: float) -> asyncio.Future[Any]:
        """A future that fails with TimeoutError after `timeout` s unless it is done before."""
        assert self._loop is not None
        waiter = self._loop.create_future()
        deadline = time.monotonic() + timeout
        self._deadlines[waiter] = deadline
        if deadline < self._deadline_at:
            if self._deadline_timer is not None:
                self._deadline_timer.cancel()
            self._deadline_at = deadline
            self._deadline_timer = self._loop.call_later(timeout, self._expire_waiters)
        return waiter

    def _expire_waiters(self) -> None:
        self._deadline_timer = None
        now = time.monotonic() + 0.001  # the loop may run a timer a hair early: do not re-arm for that
        nxt = INF
        for waiter, deadline in list(self._deadlines.items()):
            if deadline <= now:
                del self._deadlines[waiter]
                if not waiter.done():
                    waiter.set_exception(TimeoutError())
            elif deadline < nxt:
                nxt = deadline
        self._deadline_at = nxt
        if nxt < INF:
            assert self._loop is not None
            self._deadline_timer = self._loop.call_later(nxt - now, self._expire_waiters)

    def _end(self, conv: Conversation) -> None:
        if self._convs.get(conv.id) is conv:
            del self._convs[conv.id]
        self._ended[conv.id] = None
        while len(self._ended) > MAX_REMEMBERED:
            self._ended.popitem(last=False)

    def _is_ended(self, conv_id: str) -> bool:
        """A conversation we took part in and ended, or one opened by us (now or in an earlier incarnation)."""
        return conv_id in self._ended or (conv_id.startswith(self._mine) and _initiator(conv_id) == self.name)

    # ----------------------------------------------------------------- sending

    def _send_batch(self, conv: Conversation, messages: tuple[Message, ...], to: str | None) -> int:
        """Number, encode (all or nothing), transmit and track one batch; returns the conversation's next idx."""
        if not messages:
            raise MessageError("a send needs at least one message")
        if self._sock is None or self.closed:
            raise BusError(f"{self.name} is not signed on to the bus")
        conv_id, cls = conv.id, conv.cls
        allowed = catalogue.CONVERSATION_CLASSES[cls].messages
        for m in messages:  # fields were checked when message() built m; receivers check them again
            if m.name not in allowed:
                raise MessageError(f"message {m.name} does not belong to conversation {cls}")
        outs = self._out
        out = outs.get(conv_id)
        if out is None:
            out = outs[conv_id] = _Outgoing(conv._idx)
            if len(outs) > MAX_REMEMBERED:
                outs.popitem(last=False)
        else:
            outs.move_to_end(conv_id)
        start = out.next_idx
        base = out.unsettled[0][0] if out.unsettled else start
        acks: tuple[int, ...] | list[int] = ()
        to_inc = 0
        if to is not None:
            peer = self._peers.get(to)
            if peer is not None:
                key = (to, peer.inc)
                due = self._acks_due.get(key)
                if due and len(due) <= MAX_PIGGYBACK:  # more wait for their own ack datagram
                    del self._acks_due[key]
                    acks, to_inc = due, peer.inc
        n = len(messages)
        seq = self._seq
        own, encode = self._origin, wire.encode_parts
        # Encode everything before sending anything: an oversize batch fails whole, at the sender.
        try:
            if n == 1:  # the usual case, without the batch's numbering
                datas = [
                    encode(
                        own,
                        "msg",
                        seq + 1,
                        conv_id,
                        cls,
                        start,
                        0,
                        0,
                        base,
                        to,
                        messages[0].name,
                        messages[0].fields,
                        acks,
                        to_inc,
                    )
                ]
            else:
                datas = [
                    encode(
                        own,
                        "msg",
                        seq + 1 + i,
                        conv_id,
                        cls,
                        start + i,
                        n - 1 if i == 0 else 0,
                        i,
                        base,
                        to,
                        m.name,
                        m.fields,
                        acks if i == 0 else (),
                        to_inc if i == 0 else 0,
                    )
                    for i, m in enumerate(messages)
                ]
        except MessageError:
            if acks:
                self._acks_due.setdefault((to, to_inc), []).extend(acks)  # type: ignore[arg-type]
            raise
        self._seq = seq + n
        out.next_idx = start + n
        for data in datas:  # first on the wire; the bookkeeping below can wait that long
            self._transmit(data)
        waiting = {to} if to is not None else {p.name for p in self._peers.values() if cls in p.interest}
        if waiting:
            batch = [start, n]
            if out.unsettled is None:
                out.unsettled = collections.deque((batch,))
            else:
                out.unsettled.append(batch)
            now = time.monotonic()
            rto = self.cfg.ack_timeout
            pending, first_due = self._pending, self._due_first
            for i, data in enumerate(datas):
                seq += 1
                pending[seq] = _Pending(
                    data, set(waiting) if i else waiting, now, rto, batch, conv_id, cls, messages[i].name, to, base
                )
                first_due.append((now + rto, seq))
            if self._rtx_timer is None or now + rto < self._rtx_at:
                self._arm_retransmit(now + rto)
        elif to is None:
            self.log.log(
                TRACE, "%s: nobody listens to %s yet", cls, messages[0].name, extra={"conv": f"{conv_id} {cls}"}
            )
        self.stats["sent"] += n
        if self.log.isEnabledFor(TRACE):
            self.log.log(
                TRACE,
                "sent %s to %s",
                ", ".join(m.name for m in messages),
                to or "all",
                extra={"conv": f"{conv_id} {cls}"},
            )
        return out.next_idx

    def _transmit(self, data: bytes) -> None:
        """Send one datagram now. A full socket buffer loses it, like the medium would: the
        retransmission (msgs) or the next beat (hellos) makes up for it."""
        if self._sock is None:
            raise BusError(f"{self.name} is not signed on to the bus")
        try:
            self._sock.sendto(data, self._dest)
        except (BlockingIOError, InterruptedError):
            self.stats["send_lost"] += 1
        except OSError as e:
            self.stats["send_lost"] += 1
            self.log.warning("bus send failed (%s): counted as lost", e)

    def _raw_send(self, env: Envelope) -> None:
        try:
            self._transmit(wire.encode(env))
        except BusError as e:  # not signed on (closing): lost like a dropped datagram
            self.log.warning("send of %s failed: %s", env.kind, e)

    def _arm_retransmit(self, when: float) -> None:
        """(Re)arm the one retransmission timer for `when` (monotonic time)."""
        if self._rtx_timer is not None:
            self._rtx_timer.cancel()
        assert self._loop is not None
        self._rtx_at = when
        self._rtx_timer = self._loop.call_later(when - time.monotonic(), self._retransmit_due)

    def _retransmit_due(self) -> None:
        """The retransmission timer: resend every msg due and not yet acked, then re-arm for the next.

        Runs at most every ack_timeout/4, so a retransmission may come that much after its due time;
        between runs, acked msgs cost nothing but their entry, skipped here.
        """
        self._rtx_timer = None
        now = time.monotonic()
        pending, first, again = self._pending, self._due_first, self._due_again
        while first and first[0][0] <= now:
            seq = first.popleft()[1]
            if seq in pending:
                self._retransmit(seq, now)
        while again and again[0][0] <= now:
            seq = heapq.heappop(again)[1]
            if seq in pending:
                self._retransmit(seq, now)
        nxt = min(first[0][0] if first else INF, again[0][0] if again else INF)
        if nxt < INF:
            self._arm_retransmit(max(nxt, now + self.cfg.ack_timeout / 4))

    def _retransmit(self, seq: int, now: float) -> None:
        p = self._pending[seq]
        if now - p.first_sent > self.cfg.retry_deadline:
            self.stats["gave_up"] += 1
            self.log.warning(
                "gave up on %s seq %d: no ack from %s within %.1fs",
                p.msg,
                seq,
                ", ".join(sorted(p.waiting)),
                self.cfg.retry_deadline,
                extra={"conv": f"{p.conv} {p.cls}"},
            )
            self._done(seq)
            return
        self.stats["retransmitted"] += 1
        # Sent with the conversation's base as it is now, so a receiver that has no state for this stream
        # (it restarted) never waits for messages that are settled and will not come again.
        out = self._out.get(p.conv)
        if out is not None and out.base != p.base:
            p.base = out.base
            p.data = wire.encode(replace(wire.decode(p.data), base=p.base))
        self._transmit(p.data)
        p.rto = min(p.rto * 2, MAX_RTO)
        heapq.heappush(self._due_again, (now + p.rto, seq))

    def _done(self, seq: int) -> None:
        p = self._pending.pop(seq, None)
        if p is None:
            return
        batch = p.batch
        batch[1] -= 1
        if not batch[1]:
            out = self._out.get(p.conv)
            if out is not None and out.unsettled:
                unsettled = out.unsettled
                while unsettled and not unsettled[0][1]:
                    unsettled.popleft()
                if not unsettled:
                    out.unsettled = None
        if not self._pending and self._flushed is not None and not self._flushed.done():
            self._flushed.set_result(None)

    def _ack(self, key: tuple[str, int], seq: int) -> None:
        """Acknowledge soon: acks due to one peer (name, inc) go out together, or ride on our next msg to it."""
        due = self._acks_due.get(key)
        if due is None:
            self._acks_due[key] = [seq]
        else:
            due.append(seq)
        if self._ack_timer is None and self._loop is not None:
            self._ack_timer = self._loop.call_later(self.cfg.ack_timeout / 4, self._flush_acks)

    def _flush_acks(self) -> None:
        self._ack_timer = None
        due, self._acks_due = self._acks_due, {}
        for (src, inc), seqs in due.items():
            for i in range(0, len(seqs), 1000):
                self._raw_send(
                    Envelope(
                        kind="ack", src=self.name, inc=self.inc, to=src, to_inc=inc, acks=tuple(seqs[i : i + 1000])
                    )
                )

    def _hello(self, query: bool = False, to: str | None = None) -> None:
        self._raw_send(
            Envelope(
                kind="hello", src=self.name, inc=self.inc, interest=tuple(sorted(self._interest)), query=query, to=to
            )
        )

    async def _beat(self) -> None:
        """Every heartbeat: read the beats that came, send ours, then look for who went silent."""
        while True:
            await asyncio.sleep(self.cfg.heartbeat)
            try:
                self._read_beats()
                self._send_beat()
                self._expire()
            except Exception:  # a bug here must not stop the heartbeat
                self.log.exception("bus housekeeping failed")

    def _read_beats(self) -> None:
        """Beats since the last heartbeat. They are late by up to a heartbeat, so one never brings in a
        new incarnation of a module we know (that comes by its sign-on hello on the bus port), nor back
        one that said bye: a dead incarnation's last beats, read after its successor's hello or its
        own bye, must not bring it back."""
        sock, own = self._beat_sock, self._origin.prefix
        while sock is not None:
            try:
                data = sock.recv(wire.MAX_DATAGRAM + 1)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self.log.warning("bus beat socket error: %s", e)
                return
            if data.startswith(own):
                continue
            known = self._beats.get(data)
            if known is not None:  # the same beat as last time: nothing changed but the time
                peer = self._peers.get(known[0])
                if peer is not None and peer.inc == known[1]:
                    peer.last_seen = time.monotonic()
                    self.stats["beat"] += 1
                    continue
            env = self._decode(data, "beat")
            if env is None:
                continue
            if env.kind != "hello":
                self.stats["malformed"] += 1
                self.log.warning("dropped a %s from %s on the beat port", env.kind, env.src)
                continue
            self.stats["beat"] += 1
            peer = self._peers.get(env.src)
            if (peer is None and (env.src, env.inc) not in self._gone) or (peer is not None and peer.inc == env.inc):
                self._on_hello(env, peer)
                self._beats = {d: k for d, k in self._beats.items() if k[0] != env.src}
                self._beats[data] = (env.src, env.inc)

    def _send_beat(self) -> None:
        """Our hello, to the beat port: a change of interest or a query goes to the bus port instead."""
        if self._sock is None:
            return
        try:
            self._sock.sendto(
                wire.encode(
                    Envelope(kind="hello", src=self.name, inc=self.inc, interest=tuple(sorted(self._interest)))
                ),
                self._beat_dest,
            )
        except OSError as e:  # lost like a dropped datagram: the next beat makes up for it
            self.stats["send_lost"] += 1
            self.log.debug("beat not sent: %s", e)

    def _expire(self) -> None:
        now = time.monotonic()
        for name, peer in list(self._peers.items()):
            if now - peer.last_seen > self.cfg.peer_timeout:
                self._peer_left(name, "silent for %.1fs" % (now - peer.last_seen))
        # A sender retransmits for at most retry_deadline after the first send: twice that is safe.
        remember = 2 * self.cfg.retry_deadline
        horizon = now - remember
        for key, seen in list(self._seen.items()):
            if seen.since <= horizon:
                if not seen.new and not seen.old:
                    del self._seen[key]
                    continue
                seen.old, seen.new, seen.since = seen.new, set(), now
        for key, st in list(self._gaps.items()):
            if now - st.gap_since > self.cfg.retry_deadline + self.cfg.heartbeat:
                # The sender has given up on what is missing: deliver what came after it.
                self._advance(st, key, upto=min(st.buffer))
        streams = self._streams
        while streams:
            key, st = next(iter(streams.items()))
            if st.touched >= horizon:
                break
            if st.buffer or key[0] in self._convs:
                st.touched = now  # kept: looked at again `remember` from now
                streams.move_to_end(key)
            else:
                del streams[key]

    def _peer_left(self, name: str, why: str, clean: bool = False) -> None:
        peer = self._peers.pop(name, None)
        if peer is None:
            return
        self.log.info("%s left the bus (%s)", name, why)
        self._beats = {d: k for d, k in self._beats.items() if k[0] != name}
        if clean:
            self._gone[(name, peer.inc)] = None
            if len(self._gone) > MAX_GONE:
                self._gone.popitem(last=False)
        self._forget_waiting(name, directed_too=clean)
        for cb in self.peer_listeners:
            cb(name, None)

    def _forget_waiting(self, name: str, directed_too: bool, unless_cls: frozenset[str] | None = None) -> None:
        """Stop waiting for acks from `name` (broadcasts; directed sends too when it left for good)."""
        for seq, p in list(self._pending.items()):
            if name not in p.waiting or (p.to is not None and not directed_too):
                continue
            if unless_cls is not None and (p.to is not None or p.cls in unless_cls):
                continue
            p.waiting.discard(name)
            if not p.waiting:
                self._done(seq)

    # ----------------------------------------------------------------- receiving

    def _readable(self) -> None:
        """The socket has datagrams: take up to 64 (then let timers and tasks run), skip our own."""
        sock, buf, view, own = self._sock, self._buf, self._view, self._origin.prefix
        if sock is None:
            return
        handle = self._received if self._faults.active else self._handle
        for _ in range(64):
            try:
                n = sock.recv_into(buf)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self.log.warning("bus socket error: %s", e)
                return
            if n >= len(own) and buf.startswith(own):
                continue  # our own datagram, looped back by the group
            handle(bytes(view[:n]))

    def _received(self, data: bytes) -> None:
        """Every datagram when the fault injector is configured: applies it, then handles what is left."""
        r = self._rng.random()
        f = self._faults
        if r < f.drop:
            self.stats["injected_drop"] += 1
            return
        if r < f.drop + f.duplicate:
            self.stats["injected_duplicate"] += 1
            self._handle(data)
        elif r < f.drop + f.duplicate + f.reorder and self._held is None:
            self.stats["injected_reorder"] += 1
            self._held = data  # delivered after the next datagram, or after 10 ms
            assert self._loop is not None
            self._loop.call_later(0.01, self._release_held)
            return
        self._handle(data)
        self._release_held()

    def _release_held(self) -> None:
        held, self._held = self._held, None
        if held is not None:
            self._handle(held)

    def _decode(self, data: bytes, what: str) -> Envelope | None:
        """The datagram's envelope; None (counted, logged) if it is malformed."""
        try:
            return wire.decode(data)
        except MessageError as e:
            self.stats["malformed"] += 1
            self.log.warning("dropped malformed %s (%d bytes): %s", what, len(data), e)
            return None

    def _handle(self, data: bytes) -> None:
        env = self._decode(data, "datagram")
        if env is None:
            return
        if env.inc == self.inc and env.src == self.name:
            return
        try:
            now = time.monotonic()
            peer = self._peers.get(env.src)
            if peer is not None and peer.inc == env.inc:
                peer.last_seen = now  # any datagram proves life, not only hellos
            kind = env.kind
            self.stats[kind] += 1  # datagrams read, by kind: what the kernel filter let through
            if kind == "msg":
                self._on_msg(env, now)
            elif kind == "ack":
                self._on_ack(env)
            elif kind == "hello":
                self._on_hello(env, peer)
            elif peer is not None and peer.inc == env.inc:
                self._peer_left(env.src, "said bye", clean=True)
        except Exception:  # a bug must not take the receive path down with it
            self.log.exception("error handling %s from %s", env.kind, env.src)

    def _on_hello(self, env: Envelope, peer: Peer | None) -> None:
        now = time.monotonic()
        interest = frozenset(env.interest)
        if peer is None or peer.inc != env.inc:
            if peer is not None:
                # The old process is gone. Listeners get the new Peer (its inc differs from the one they
                # knew); msgs still waiting for the old one are acked by the new one and dropped as late.
                self.log.info("%s restarted (incarnation %x -> %x)", env.src, peer.inc, env.inc)
            else:
                self.log.info("%s joined the bus", env.src)
            peer = Peer(env.src, env.inc, interest, now)
            self._peers[env.src] = peer
            for cb in self.peer_listeners:
                cb(env.src, peer)
        else:
            if interest != peer.interest:
                peer.interest = interest
                # It no longer listens to some classes: it will not ack broadcasts of them.
                self._forget_waiting(env.src, directed_too=False, unless_cls=interest)
            peer.last_seen = now
        if env.query:  # addressed to the newcomer: N answers to one module, not N x N receptions
            self._hello(to=env.src)

    def _on_ack(self, env: Envelope) -> None:
        if env.to != self.name or env.to_inc != self.inc:
            return
        self._acked(env.src, env.acks)

    def _acked(self, src: str, seqs: Iterable[int]) -> None:
        pending = self._pending
        for seq in seqs:
            p = pending.get(seq)
            if p is not None:
                p.waiting.discard(src)
                if not p.waiting:
                    self._done(seq)

    def _on_msg(self, env: Envelope, now: float) -> None:
        to, src, inc = env.to, env.src, env.inc
        if to is not None and to != self.name:
            return
        if env.acks and to is not None and env.to_inc == self.inc:
            self._acked(src, env.acks)
        conv_id = env.conv
        conv = self._convs.get(conv_id)
        if to is None and conv is None and env.cls not in self._interest:
            return  # not for us: no ack, the sender does not count us
        seq = env.seq
        key = (src, inc)
        self._ack(key, seq)
        seen = self._seen.get(key)
        if seen is None:
            seen = self._seen[key] = _Seen(now)
        elif seq in seen.new or seq in seen.old:
            self.stats["duplicates"] += 1
            return
        seen.new.add(seq)
        if conv is None and self._is_ended(conv_id):
            self.stats["late"] += 1
            self.log.warning(
                "late %s from %s in ended conversation: dropped", env.msg, src, extra={"conv": f"{conv_id} {env.cls}"}
            )
            return
        try:
            msg: Message | None = catalogue.check(env.cls, env.msg, env.fields)
        except MessageError as e:
            # Still take its place in the order, so the messages after it are not held up forever.
            self.stats["invalid"] += 1
            self.log.warning("dropped invalid %s from %s: %s", env.msg, src, e, extra={"conv": f"{conv_id} {env.cls}"})
            msg = None
        skey = (conv_id, src, inc)
        streams = self._streams
        st = streams.get(skey)
        if st is None:
            # No state for this stream (first contact, or we restarted): what is below base is settled.
            st = streams[skey] = _Stream(env.base, now)
        else:
            st.touched = now
            streams.move_to_end(skey)
        idx = env.idx
        if idx < st.next_idx:  # a new seq for a place already passed: never sent by a well-behaved peer
            self.log.warning(
                "dropped %s from %s: idx %d is behind the stream (%d)",
                env.msg,
                src,
                idx,
                st.next_idx,
                extra={"conv": f"{conv_id} {env.cls}"},
            )
            return
        if idx == st.next_idx and not env.more and not env.part and not st.buffer and not st.batch:
            st.next_idx += 1  # the usual case: a one-message batch, in order, nothing waiting
            self._deliver(env, conv, (msg,))
            return
        if not st.buffer:
            st.gap_since = now
            self._gaps[skey] = st
        st.buffer[idx] = (env, msg)
        self._advance(st, skey, upto=env.base)

    def _advance(self, st: _Stream, skey: tuple[str, str, int], upto: int = 0) -> None:
        """Deliver what is in order; a message missing below `upto` is settled elsewhere: skip it."""
        lost = 0
        while True:
            item = st.buffer.pop(st.next_idx, None)
            if item is None:
                if st.next_idx >= upto:
                    break
                target = min(min(st.buffer, default=upto), upto)
                lost += target - st.next_idx
                st.next_idx = target
                st.batch = None  # a batch with a hole in it is never delivered
                continue
            st.next_idx += 1
            env = item[0]
            batch = st.batch
            if env.part == 0:
                if batch:
                    lost += len(batch)
                batch = st.batch = [item]
            elif batch and env.part == len(batch):
                batch.append(item)
            else:
                lost += 1  # the rest of a batch whose beginning was lost
                continue
            if len(batch) == batch[0][0].more + 1:
                st.batch = None
                head = batch[0][0]
                self._deliver(head, self._convs.get(head.conv), tuple(m for _, m in batch))
        if not st.buffer:
            self._gaps.pop(skey, None)
        if lost:
            self.stats["gaps"] += 1
            self.log.warning(
                "%d message(s) from %s never arrived (the sender gave up on them); going on",
                lost,
                skey[1],
                extra={"conv": skey[0]},
            )

    def _deliver(self, head: Envelope, conv: Conversation | None, msgs: tuple[Message | None, ...]) -> None:
        for m in msgs:
            if m is None:
                self.log.warning(
                    "dropped a batch of %d from %s: it holds an invalid message",
                    len(msgs),
                    head.src,
                    extra={"conv": f"{head.conv} {head.cls}"},
                )
                return
        self.stats["delivered"] += 1
        batch = Batch(head.src, msgs)  # type: ignore[arg-type]
        if conv is not None:
            conv._put(batch)
            return
        if head.to is None and head.cls not in self._interest:
            return
        if head.msg != catalogue.CONVERSATION_CLASSES[head.cls].messages[0]:
            self.stats["stray"] += 1
            self.log.warning(
                "stray %s from %s: not the opening of %s and no such conversation here",
                head.msg,
                head.src,
                head.cls,
                extra={"conv": f"{head.conv} {head.cls}"},
            )
            return
        conv = Conversation(self, head.conv, head.cls, head.src, first=batch)
        self._convs[conv.id] = conv
        self._put_incoming(conv)


def _initiator(conv_id: str) -> str | None:
    """The module that opened a conversation, from its id '<initiator>.<inc hex>.<n>'."""
    parts = conv_id.rsplit(".", 2)
    return parts[0] if len(parts) == 3 else None


class BlockingBus:
    """A Bus running in its own thread, for code that is not asyncio (lot scripts, the HI, tests).

    Every method is the Bus's own coroutine run on that thread's loop; nothing is reimplemented.
    """

    def __init__(self, name: str, cfg: BusConfig, log: logging.Logger, interest: Iterable[str] = ()) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name=f"bus-{name}", daemon=True)
        self._thread.start()
        self.bus: Bus = self.run(self._make(name, cfg, log, interest))
        self._closed = False

    @staticmethod
    async def _make(name: str, cfg: BusConfig, log: logging.Logger, interest: Iterable[str]) -> Bus:
        bus = Bus(name, cfg, log, interest)
        await bus.sign_on()
        return bus

    def run(self, coro: Coroutine[Any, Any, T], timeout: float | None = None) -> T:
        """Run a coroutine on the bus's loop (one that uses self.bus) and return its result."""
        fut = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return fut.result(timeout)

    def call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        self._loop.call_soon_threadsafe(fn, *args)

    def start(self, cls: str, *messages: Message, to: str | None = None) -> BlockingConversation:
        return BlockingConversation(self, self.run(self.bus.start(cls, *messages, to=to)))

    def request(
        self, cls: str, *messages: Message, to: str | None = None, timeout: float | None = None
    ) -> tuple[BlockingConversation, Batch]:
        conv, batch = self.run(self.bus.request(cls, *messages, to=to, timeout=timeout))
        return BlockingConversation(self, conv), batch

    def resume(self, conv_id: str, cls: str, peer: str) -> BlockingConversation:
        async def _resume() -> Conversation:
            return self.bus.resume(conv_id, cls, peer)

        return BlockingConversation(self, self.run(_resume()))

    def first_message(self, timeout: float | None = None) -> BlockingConversation | None:
        conv = self.run(self.bus.first_message(timeout))
        return BlockingConversation(self, conv) if conv else None

    def set_interest(self, classes: Iterable[str]) -> None:
        """Change the interest filter; returns once it applies (unknown classes raise here)."""

        async def _set() -> None:
            self.bus.set_interest(list(classes))

        self.run(_set())

    def peers(self) -> dict[str, Peer]:
        async def _peers() -> dict[str, Peer]:
            return self.bus.peers()

        return self.run(_peers())

    def close(self) -> None:
        """Flush, sign off and stop the thread. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self.run(self.bus.close(), timeout=5)
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5)
            self._loop.close()

    def __enter__(self) -> BlockingBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class BlockingConversation:
    """A Conversation driven from another thread through its BlockingBus."""

    def __init__(self, owner: BlockingBus, conv: Conversation) -> None:
        self._owner = owner
        self.conv = conv

    @property
    def id(self) -> str:
        return self.conv.id

    @property
    def cls(self) -> str:
        return self.conv.cls

    @property
    def first(self) -> Batch | None:
        return self.conv.first

    @property
    def peer(self) -> str | None:
        return self.conv.peer

    def send(self, *messages: Message, to: str | None = _DEFAULT) -> None:
        self._owner.run(self.conv.send(*messages, to=to))

    def next_message(self, timeout: float | None = None) -> Batch:
        return self._owner.run(self.conv.next_message(timeout))

    def expect(self, *names: str, timeout: float | None = None) -> Batch:
        return self._owner.run(self.conv.expect(*names, timeout=timeout))

    def end(self) -> None:
        self._owner.call_soon(self.conv.end)
