"""The CELL bus: reliable conversations over UDP multicast (the successor of the thesis's ISIS bus).

Every module joins one multicast group. A conversation is started by one module and broadcast to
every module interested in its class (or addressed to one module); answers travel in the same
conversation, addressed to the other side. On top of lossy UDP the bus gives:

* reliability: every msg datagram is acknowledged by each module it is meant for; unacknowledged
  datagrams are retransmitted (exponential backoff) until acked or `retry_deadline` passes;
* exactly-once delivery: duplicates are recognised by (sender, incarnation, seq), re-acked, not
  delivered again, so a repeated request never causes a second action;
* order: each sender's messages in a conversation are delivered in the order sent; a batch (a first
  message saying `more` follow, e.g. Machine_Request + N x Machine_Entry) is delivered whole;
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
import logging
import random
import socket
import struct
import threading
import time
from collections.abc import Callable, Coroutine, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from gwc.config import BusConfig
from gwc.errors import BusError, ConversationTimeout, MessageError
from gwc.ipc import catalogue, wire
from gwc.ipc.catalogue import Message
from gwc.ipc.wire import Envelope

T = TypeVar("T")
_DEFAULT: Any = object()
RCVBUF = 4 * 1024 * 1024
MAX_RTO = 0.5


def open_socket(cfg: BusConfig) -> socket.socket:
    """A UDP socket joined to the cell's group on its interface; closed again if any step fails."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
        sock.bind(("", cfg.port))
        iface = socket.inet_aton(cfg.interface)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(cfg.group) + iface)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, iface)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("b", 1))
        sock.setblocking(False)
    except OSError as e:
        sock.close()
        raise BusError(f"cannot join bus group {cfg.group}:{cfg.port} on {cfg.interface}: {e}") from e
    return sock


@dataclass
class Peer:
    name: str
    inc: int
    interest: frozenset[str]
    last_seen: float


@dataclass
class _Pending:
    data: bytes
    env: Envelope
    waiting: set[str]
    first_sent: float
    rto: float
    timer: asyncio.TimerHandle | None = None


@dataclass
class _Stream:
    """Per (conversation, sender, incarnation): reorder buffer and the batch being assembled."""

    next_idx: int = 0
    buffer: dict[int, tuple[Envelope, Message | None]] = field(default_factory=dict)
    batch: list[tuple[Envelope, Message | None]] = field(default_factory=list)
    remaining: int = 0
    touched: float = 0.0


@dataclass(frozen=True)
class Batch:
    """Messages delivered together: a first message and the `more` that followed it."""

    sender: str
    messages: tuple[Message, ...]

    @property
    def first(self) -> Message:
        return self.messages[0]


class Conversation:
    """One conversation as seen by one module: send into it, wait for the other side's messages."""

    def __init__(self, bus: Bus, conv_id: str, cls: str, initiator: str, first: Batch | None = None) -> None:
        self.bus = bus
        self.id = conv_id
        self.cls = cls
        self.initiator = initiator
        self.first = first  # for an incoming conversation: the batch that opened it
        self.peer: str | None = first.sender if first else None
        self._inbox: asyncio.Queue[Batch] = asyncio.Queue()
        self._idx = 0
        self.ended = False

    @property
    def incoming(self) -> bool:
        return self.first is not None

    def __repr__(self) -> str:
        return f"<Conversation {self.cls} {self.id}>"

    async def send(self, *messages: Message, to: str | None = _DEFAULT) -> None:
        """Send a batch into this conversation; by default to the other side (or to all, if unknown)."""
        target = self.peer if to is _DEFAULT else to
        self._idx = self.bus._send_batch(self, list(messages), target, self._idx)

    async def next_message(self, timeout: float | None = None) -> Batch:
        """The next batch the other side sends; ConversationTimeout (logged) if none comes in time."""
        t = self.bus.cfg.reply_timeout if timeout is None else timeout
        try:
            batch = await asyncio.wait_for(self._inbox.get(), t)
        except asyncio.TimeoutError:
            who = self.peer or f"any module listening to {self.cls}"
            err = ConversationTimeout(f"{self.cls} conversation {self.id}: no answer from {who} within {t:.1f}s")
            self.bus.log.error("%s", err, extra={"conv": f"{self.id} {self.cls}"})
            raise err from None
        self.peer = batch.sender
        return batch

    async def expect(self, *names: str, timeout: float | None = None) -> Batch:
        """next_message(), checked to be one of the named message classes."""
        batch = await self.next_message(timeout)
        if names and batch.first.name not in names:
            raise MessageError(
                f"{self.cls} {self.id}: expected {' or '.join(names)}, got {batch.first.name} from {batch.sender}"
            )
        return batch

    def end(self) -> None:
        """Stop routing messages to this conversation (late ones are logged and dropped)."""
        if not self.ended:
            self.ended = True
            self.bus._convs.pop(self.id, None)


class Bus:
    """One module's attachment to the CELL bus (see the module docstring)."""

    def __init__(
        self,
        name: str,
        cfg: BusConfig,
        log: logging.Logger,
        interest: Iterable[str] = (),
    ) -> None:
        self.name = name
        self.cfg = cfg
        self.log = log
        self.inc = random.SystemRandom().randrange(1, 2**31)
        self._interest: set[str] = set()
        self.set_interest(interest, announce=False)
        self._seq = 0
        self._conv_n = 0
        self._sock: socket.socket | None = None
        self._transport: asyncio.DatagramTransport | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._peers: dict[str, Peer] = {}
        self._pending: dict[int, _Pending] = {}
        self._seen: dict[tuple[str, int], tuple[set[int], collections.deque[tuple[float, int]]]] = {}
        self._streams: dict[tuple[str, str, int], _Stream] = {}
        self._convs: dict[str, Conversation] = {}
        self._incoming: asyncio.Queue[Conversation] = asyncio.Queue()
        self._heartbeat: asyncio.Task[None] | None = None
        self._faults = cfg.faults
        self._rng = random.Random(cfg.faults.seed)
        self._held: bytes | None = None
        self._flushed: asyncio.Event | None = None  # created on sign_on, inside the loop
        self.peer_listeners: list[Callable[[str, Peer | None], None]] = []
        self.stats = collections.Counter[str]()
        self.closed = False

    # ----------------------------------------------------------------- lifecycle

    async def sign_on(self, settle: float = 0.05) -> None:
        """Join the group, announce ourselves, and give present modules `settle` s to answer."""
        self._loop = asyncio.get_running_loop()
        self._sock = open_socket(self.cfg)
        self._flushed = asyncio.Event()
        self._flushed.set()
        transport, _ = await self._loop.create_datagram_endpoint(lambda: _Protocol(self), sock=self._sock)
        self._transport = transport  # type: ignore[assignment]
        self._hello(query=True)
        self._heartbeat = self._loop.create_task(self._beat())
        self.log.info("signed on to bus %s as %s (incarnation %x)", self.cfg.name, self.name, self.inc)
        if settle:
            await asyncio.sleep(settle)

    async def close(self, flush: float = 1.0) -> None:
        """Wait up to `flush` s for outstanding acks, say bye, leave. Safe to call twice."""
        if self.closed:
            return
        self.closed = True
        if flush and self._pending and self._flushed is not None:
            try:
                await asyncio.wait_for(self._flushed.wait(), flush)
            except asyncio.TimeoutError:
                self.log.warning("closing with %d datagram(s) unacknowledged", len(self._pending))
        if self._heartbeat:
            self._heartbeat.cancel()
        for p in self._pending.values():
            if p.timer:
                p.timer.cancel()
        self._pending.clear()
        if self._transport:
            self._raw_send(Envelope(kind="bye", src=self.name, inc=self.inc))
            self._transport.close()
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
        if announce and self._transport:
            self._hello()

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
        return f"{self.name}.{self.inc:x}.{self._conv_n}"

    async def start(self, cls: str, *messages: Message, to: str | None = None) -> Conversation:
        """Open a conversation and send its first batch (broadcast to listeners of cls, or to one module)."""
        if cls not in catalogue.CONVERSATION_CLASSES:
            raise MessageError(f"unknown conversation class {cls!r}")
        conv = Conversation(self, self._new_conv_id(), cls, self.name)
        self._convs[conv.id] = conv
        try:
            await conv.send(*messages, to=to)
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
        conv = self._convs.get(conv_id)
        if conv is None:
            conv = Conversation(self, conv_id, cls, peer)
            conv.peer = peer
            self._convs[conv_id] = conv
        return conv

    async def first_message(self, timeout: float | None = None) -> Conversation | None:
        """The next conversation another module opened with us; None after timeout."""
        try:
            return await asyncio.wait_for(self._incoming.get(), timeout)
        except asyncio.TimeoutError:
            return None

    # ----------------------------------------------------------------- sending

    def _send_batch(self, conv: Conversation, messages: list[Message], to: str | None, idx: int) -> int:
        if not messages:
            raise MessageError("a send needs at least one message")
        cc = catalogue.CONVERSATION_CLASSES[conv.cls]
        envs = []
        for i, m in enumerate(messages):
            if m.name not in cc.messages:
                raise MessageError(f"message {m.name} does not belong to conversation {conv.cls}")
            self._seq += 1
            envs.append(
                Envelope(
                    kind="msg", src=self.name, inc=self.inc, seq=self._seq, conv=conv.id, cls=conv.cls,
                    idx=idx + i, more=len(messages) - 1 if i == 0 else 0, to=to, msg=m.name, fields=m.fields,
                )
            )
        # Encode everything before sending anything: an oversize batch fails whole, at the sender.
        datas = [wire.encode(e) for e in envs]
        waiting = {to} if to is not None else set(self.listeners_of(conv.cls))
        now = time.monotonic()
        for env, data in zip(envs, datas):
            self._transmit(data)
            self.stats["sent"] += 1
            if waiting:
                p = _Pending(data, env, set(waiting), now, self.cfg.ack_timeout)
                self._pending[env.seq] = p
                assert self._loop is not None
                p.timer = self._loop.call_later(p.rto, self._retransmit, env.seq)
                if self._flushed:
                    self._flushed.clear()
            self.log.log(5, "sent %s to %s", env.msg, to or "all", extra={"conv": f"{conv.id} {conv.cls}"})
        return idx + len(messages)

    def _transmit(self, data: bytes) -> None:
        if self._transport is None:
            raise BusError(f"{self.name} is not signed on to the bus")
        self._transport.sendto(data, (self.cfg.group, self.cfg.port))

    def _raw_send(self, env: Envelope) -> None:
        try:
            self._transmit(wire.encode(env))
        except OSError as e:  # a full socket buffer loses this one; retransmission or the next beat covers it
            self.log.warning("send of %s failed: %s", env.kind, e)

    def _retransmit(self, seq: int) -> None:
        p = self._pending.get(seq)
        if p is None:
            return
        if time.monotonic() - p.first_sent > self.cfg.retry_deadline:
            self.log.warning(
                "gave up on %s seq %d: no ack from %s within %.1fs",
                p.env.msg, seq, ", ".join(sorted(p.waiting)), self.cfg.retry_deadline,
                extra={"conv": f"{p.env.conv} {p.env.cls}"},
            )
            self._done(seq)
            return
        self.stats["retransmitted"] += 1
        try:
            self._transmit(p.data)
        except OSError:
            pass
        p.rto = min(p.rto * 2, MAX_RTO)
        assert self._loop is not None
        p.timer = self._loop.call_later(p.rto, self._retransmit, seq)

    def _done(self, seq: int) -> None:
        p = self._pending.pop(seq, None)
        if p and p.timer:
            p.timer.cancel()
        if not self._pending and self._flushed:
            self._flushed.set()

    def _hello(self, query: bool = False) -> None:
        self._raw_send(Envelope(kind="hello", src=self.name, inc=self.inc, interest=tuple(sorted(self._interest)),
                                query=query))

    async def _beat(self) -> None:
        while True:
            await asyncio.sleep(self.cfg.heartbeat)
            self._hello()
            self._expire()

    def _expire(self) -> None:
        now = time.monotonic()
        for name, peer in list(self._peers.items()):
            if now - peer.last_seen > self.cfg.peer_timeout:
                self._peer_left(name, "silent for %.1fs" % (now - peer.last_seen))
        horizon = now - 2 * self.cfg.retry_deadline
        for key, (seen, order) in list(self._seen.items()):
            while order and order[0][0] < horizon:
                seen.discard(order.popleft()[1])
            if not order:
                del self._seen[key]
        for key, st in list(self._streams.items()):
            if st.touched < horizon and not st.buffer and not st.batch:
                del self._streams[key]

    def _peer_left(self, name: str, why: str, clean: bool = False) -> None:
        peer = self._peers.pop(name, None)
        if peer is None:
            return
        self.log.info("%s left the bus (%s)", name, why)
        for seq, p in list(self._pending.items()):
            # A silent peer may be restarting: directed sends keep trying until their deadline.
            if p.env.to is None or clean:
                p.waiting.discard(name)
                if not p.waiting:
                    self._done(seq)
        for cb in self.peer_listeners:
            cb(name, None)

    # ----------------------------------------------------------------- receiving

    def _received(self, data: bytes) -> None:
        """Entry point for every datagram; applies the fault injector when configured."""
        if self._faults.active:
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
        else:
            self._handle(data)

    def _release_held(self) -> None:
        held, self._held = self._held, None
        if held is not None:
            self._handle(held)

    def _handle(self, data: bytes) -> None:
        try:
            env = wire.decode(data)
        except MessageError as e:
            self.stats["malformed"] += 1
            self.log.warning("dropped malformed datagram (%d bytes): %s", len(data), e)
            return
        if env.src == self.name and env.inc == self.inc:
            return
        try:
            if env.kind == "msg":
                self._on_msg(env)
            elif env.kind == "ack":
                self._on_ack(env)
            elif env.kind == "hello":
                self._on_hello(env)
            else:
                self._peer_left(env.src, "said bye", clean=True)
        except Exception:  # a bug must not take the receive path down with it
            self.log.exception("error handling %s from %s", env.kind, env.src)

    def _on_hello(self, env: Envelope) -> None:
        now = time.monotonic()
        peer = self._peers.get(env.src)
        if peer is None or peer.inc != env.inc:
            if peer is not None:
                self.log.info("%s restarted (incarnation %x -> %x)", env.src, peer.inc, env.inc)
            else:
                self.log.info("%s joined the bus", env.src)
            peer = Peer(env.src, env.inc, frozenset(env.interest), now)
            self._peers[env.src] = peer
            for cb in self.peer_listeners:
                cb(env.src, peer)
        else:
            peer.interest = frozenset(env.interest)
            peer.last_seen = now
        if env.query:
            self._hello()

    def _on_ack(self, env: Envelope) -> None:
        if env.to != self.name or env.to_inc != self.inc:
            return
        for seq in env.acks:
            p = self._pending.get(seq)
            if p is not None:
                p.waiting.discard(env.src)
                if not p.waiting:
                    self._done(seq)

    def _on_msg(self, env: Envelope) -> None:
        if env.to is not None and env.to != self.name:
            return
        if env.to is None and env.cls not in self._interest and env.conv not in self._convs:
            return  # not for us: no ack, the sender does not count us
        self._raw_send(Envelope(kind="ack", src=self.name, inc=self.inc, to=env.src, to_inc=env.inc, acks=(env.seq,)))
        key = (env.src, env.inc)
        seen, order = self._seen.setdefault(key, (set(), collections.deque()))
        if env.seq in seen:
            self.stats["duplicates"] += 1
            return
        seen.add(env.seq)
        now = time.monotonic()
        order.append((now, env.seq))
        try:
            msg: Message | None = catalogue.check(env.cls, env.msg, env.fields)
        except MessageError as e:
            # Still take its place in the order, so the messages after it are not held up forever.
            self.stats["invalid"] += 1
            self.log.warning("dropped invalid %s from %s: %s", env.msg, env.src, e,
                             extra={"conv": f"{env.conv} {env.cls}"})
            msg = None
        st = self._streams.setdefault((env.conv, env.src, env.inc), _Stream())
        st.touched = now
        if env.idx < st.next_idx:
            return
        st.buffer[env.idx] = (env, msg)
        while st.next_idx in st.buffer:
            item = st.buffer.pop(st.next_idx)
            st.next_idx += 1
            if not st.batch:
                st.remaining = item[0].more
            else:
                st.remaining -= 1
            st.batch.append(item)
            if st.remaining <= 0:
                batch, st.batch = st.batch, []
                self._deliver(batch)

    def _deliver(self, items: list[tuple[Envelope, Message | None]]) -> None:
        head = items[0][0]
        msgs = tuple(m for _, m in items if m is not None)
        if not msgs:
            return
        self.stats["delivered"] += 1
        batch = Batch(head.src, msgs)
        conv = self._convs.get(head.conv)
        if conv is not None:
            conv._inbox.put_nowait(batch)
            return
        if head.to is None and head.cls not in self._interest:
            return
        conv = Conversation(self, head.conv, head.cls, head.src, first=batch)
        self._convs[conv.id] = conv
        self._incoming.put_nowait(conv)


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.bus._received(data)

    def error_received(self, exc: Exception) -> None:
        self.bus.log.warning("bus socket error: %s", exc)


class BlockingBus:
    """A Bus running in its own thread, for code that is not asyncio (lot scripts, the HI, tests).

    Every method is the Bus's own coroutine run on that thread's loop; nothing is reimplemented.
    """

    def __init__(self, name: str, cfg: BusConfig, log: logging.Logger, interest: Iterable[str] = ()) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name=f"bus-{name}", daemon=True)
        self._thread.start()
        self.bus: Bus = self._call(self._make(name, cfg, log, interest))
        self._closed = False

    @staticmethod
    async def _make(name: str, cfg: BusConfig, log: logging.Logger, interest: Iterable[str]) -> Bus:
        bus = Bus(name, cfg, log, interest)
        await bus.sign_on()
        return bus

    def _call(self, coro: Coroutine[Any, Any, T], timeout: float | None = None) -> T:
        fut = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return fut.result(timeout)

    def call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        self._loop.call_soon_threadsafe(fn, *args)

    def start(self, cls: str, *messages: Message, to: str | None = None) -> BlockingConversation:
        return BlockingConversation(self, self._call(self.bus.start(cls, *messages, to=to)))

    def request(
        self, cls: str, *messages: Message, to: str | None = None, timeout: float | None = None
    ) -> tuple[BlockingConversation, Batch]:
        conv, batch = self._call(self.bus.request(cls, *messages, to=to, timeout=timeout))
        return BlockingConversation(self, conv), batch

    def resume(self, conv_id: str, cls: str, peer: str) -> BlockingConversation:
        async def _resume() -> Conversation:
            return self.bus.resume(conv_id, cls, peer)

        return BlockingConversation(self, self._call(_resume()))

    def first_message(self, timeout: float | None = None) -> BlockingConversation | None:
        conv = self._call(self.bus.first_message(timeout))
        return BlockingConversation(self, conv) if conv else None

    def set_interest(self, classes: Iterable[str]) -> None:
        self._loop.call_soon_threadsafe(self.bus.set_interest, list(classes))

    def peers(self) -> dict[str, Peer]:
        async def _peers() -> dict[str, Peer]:
            return self.bus.peers()

        return self._call(_peers())

    def close(self) -> None:
        """Flush, sign off and stop the thread. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self._call(self.bus.close(), timeout=5)
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
        self._owner._call(self.conv.send(*messages, to=to))

    def next_message(self, timeout: float | None = None) -> Batch:
        return self._owner._call(self.conv.next_message(timeout))

    def expect(self, *names: str, timeout: float | None = None) -> Batch:
        return self._owner._call(self.conv.expect(*names, timeout=timeout))

    def end(self) -> None:
        self._owner.call_soon(self.conv.end)
