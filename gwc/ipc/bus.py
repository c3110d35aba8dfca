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
import logging
import random
import time
from collections.abc import Callable, Iterable, Mapping

from gwc.config import BusConfig
from gwc.errors import BusError, MessageError
from gwc.ipc import catalogue, wire
from gwc.ipc.auth import Guard
from gwc.ipc.catalogue import Message
from gwc.ipc.codes import AckCode
from gwc.ipc.conversation import CLOSED, Batch, Conversation, Deadlines, Names, Peer, initiator
from gwc.ipc.membership import Membership, tick
from gwc.ipc.order import Inbound
from gwc.ipc.outbox import MAX_REMEMBERED, Outbox
from gwc.ipc.transport import FaultInjector, Transport, UdpTransport
from gwc.ipc.wire import Envelope
from gwc.log import TRACE, FaultLog

__all__ = ["Batch", "Bus", "Conversation", "Peer"]

# Looked up on every msg sent or received: (conversation class, message class) -> the message class, the
# message classes each conversation class allows, and the one that opens it.
_MEMBERS = catalogue.MEMBERS
_ALLOWED = {c.name: frozenset(c.messages) for c in catalogue.CONVERSATION_CLASSES.values()}
_OPENERS = {c.name: c.messages[0] for c in catalogue.CONVERSATION_CLASSES.values()}


class Bus:
    """One module's attachment to the CELL bus (see the module docstring)."""

    def __init__(
        self,
        name: str,
        cfg: BusConfig,
        log: logging.Logger,
        interest: Iterable[str] = (),
        transport: Transport | None = None,
        ignored_peers: Names = (),
    ) -> None:
        if not name or len(name) > wire.MAX_NAME - 30:
            raise BusError(f"bad bus module name {name!r}")
        self.name = name
        self.cfg = cfg
        self.log = log
        self.inc = random.SystemRandom().randrange(1, 2**31)
        self._interest: set[str] = set()
        self._subjects: dict[str, frozenset[str]] = {}  # class -> the only subjects heard of it (set_interest)
        self.stats = collections.Counter[str]()
        self.transport = UdpTransport(cfg, log) if transport is None else transport
        self._open = False  # the transport is open (signed on, not yet closed)
        self._seq = self._conv_n = 0  # the last msg seq and conversation number used
        self._loop: asyncio.AbstractEventLoop | None = None
        self._faults = FaultInjector(cfg.faults, name, self.stats)
        self.guard = Guard(cfg, name, log, self.stats)  # signs what we send, checks what we receive
        self.outbox = Outbox(name, self.inc, cfg, log, self.stats, self._transmit)  # acks, retransmission
        self.ignored_peers = ignored_peers  # prefixes of the names of peers not tracked (docs/protocol.md)
        self._members = Membership(self)
        self._peers = self._members.peers  # the same dict: read on the hot paths
        self.set_interest(interest, announce=False)
        self._inbound = Inbound(cfg, log, self.stats, self._deliver)
        self._convs: dict[str, Conversation] = {}
        self._ended: collections.OrderedDict[str, None] = collections.OrderedDict()
        # New conversations, and the first_message() calls waiting for one (no asyncio.Queue: hot path).
        self._incoming: collections.deque[Conversation] = collections.deque()
        self._incoming_waiters: collections.deque[asyncio.Future[Conversation]] = collections.deque()
        self._accept: Callable[[Conversation], None] | None = None  # accept(): new conversations go there
        self.deadlines = Deadlines()  # every wait's deadline, on one timer
        self._heartbeat: asyncio.Task[None] | None = None
        self.faults = FaultLog(log, self.stats)  # a step that failed: counted, logged once per kind
        self._origin = wire.origin(name, self.inc)
        self._speaking = wire.VERSION  # the wire version we encode in (speak(); docs/protocol.md, Versions)
        self._mine = f"{name}."  # how the ids of conversations this module opened begin
        self._conv_prefix = f"{name}.{self.inc:x}."  # ... in this incarnation
        self.peer_listeners: list[Callable[[str, Peer | None], None]] = []  # told of every join and leave
        # Told after every heartbeat: a module's periodic work rides on the beat's wake-up, not a timer of its own.
        self.beat_listeners: list[Callable[[], None]] = []
        self.closed = False

    # ----------------------------------------------------------------- lifecycle

    async def sign_on(self, settle: float = 0.05) -> None:
        """Join the group, announce ourselves, and give present modules `settle` s to answer."""
        loop = self._loop = self.deadlines.loop = self.outbox.loop = asyncio.get_running_loop()
        self._open = True  # the transport may hand over datagrams before open() returns: we can answer
        try:
            await self.transport.open(loop, self._origin.prefix, self._faults.wrap(loop, self._handle))
        except BaseException:
            self._open = False
            raise
        self.transport.set_filter(self.name, self.inc, self._interest, self.ignored_peers, self._subjects)
        self.transport.ignore_beats_from(self.ignored_peers)
        self._members.hello(query=True)
        self._heartbeat = loop.create_task(self._beat())
        self.log.info("signed on to bus %s as %s (incarnation %x)", self.cfg.name, self.name, self.inc)
        if settle:
            await asyncio.sleep(settle)

    async def close(self, flush: float = 1.0) -> None:
        """Wait up to `flush` s for outstanding acks, say bye, leave; every waiter fails. Safe to call twice."""
        if self.closed:
            return
        self.closed = True
        self.outbox.flush_acks()
        await self.outbox.drain(flush)
        if self._heartbeat is not None:
            self._heartbeat.cancel()
        self.outbox.close()
        self.deadlines.cancel()
        if self._open:
            self.outbox.send_envelope(Envelope(kind="bye", src=self.name, inc=self.inc))
            self._open = False
        self.transport.close()
        for conv in self._convs.values():
            conv.deliver(CLOSED)
        self._put_incoming(CLOSED)
        self.log.info("signed off bus %s", self.cfg.name)

    # ----------------------------------------------------------------- interest filters

    @property
    def interests(self) -> frozenset[str]:
        return frozenset(self._interest)

    @property
    def subjects(self) -> Mapping[str, frozenset[str]]:
        """Class -> the only subjects this module hears of it (set_interest)."""
        return self._subjects

    @property
    def signed_on(self) -> bool:
        """Joined and not yet closed: datagrams may be sent."""
        return self._open

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the bus runs on (BusError before sign-on)."""
        if self._loop is None:
            raise BusError(f"{self.name} has not signed on to the bus")
        return self._loop

    def set_interest(
        self, classes: Iterable[str], announce: bool = True, subjects: Mapping[str, Iterable[str]] | None = None
    ) -> None:
        """Listen to exactly these conversation classes from now on (thesis: interest/no_interest), and to
        the classes of `subjects` about the subjects named there only (a lot, about its own machines:
        docs/protocol.md, "Subjects"). A class in both is heard whole."""
        new = set(classes)
        about = {c: frozenset(s) for c, s in (subjects or {}).items() if c not in new}
        about = {c: s for c, s in about.items() if s}
        unknown = (new | set(about)) - set(catalogue.CONVERSATION_CLASSES)
        if unknown:
            raise MessageError(f"unknown conversation class(es): {', '.join(sorted(unknown))}")
        not_about = set(about) - set(catalogue.SUBJECT_FIELDS)
        if not_about:
            raise MessageError(f"class(es) {', '.join(sorted(not_about))} name no subject: listen to them whole")
        if new == self._interest and about == self._subjects:
            return
        self._interest = new
        self._subjects = about
        self._members.beat_body = None
        if self._open:
            self.transport.set_filter(self.name, self.inc, new, self.ignored_peers, about)
            if announce:
                self._members.hello()

    def interest(self, *classes: str) -> None:
        self.set_interest(self._interest | set(classes), subjects=self._subjects)

    def no_interest(self, *classes: str) -> None:
        self.set_interest(self._interest - set(classes), subjects=self._subjects)

    def peers(self) -> dict[str, Peer]:
        return dict(self._peers)

    # ----------------------------------------------------------------- wire versions (gwc/ipc/membership.py)

    @property
    def speaking(self) -> int:
        """The wire version this bus encodes in now: the lowest its peers speak, at most its own."""
        return self._speaking

    def versions(self) -> dict[str, int]:
        """Peer name -> the highest wire version it speaks (from its hellos)."""
        return dict(self._members.speaks)

    def speak(self, version: int) -> None:
        """Encode everything from now on in wire `version` (the membership decides which): what is
        already in flight is retransmitted as it was encoded."""
        self._origin = self._origin_in(version)
        self._speaking = self.outbox.version = version

    def _origin_in(self, version: int) -> wire.Origin:
        omit = catalogue.fields_after(version) if version < wire.VERSION else None
        return wire.origin(self.name, self.inc, version, omit)

    def listeners_of(self, cls: str, subject: str = "") -> list[str]:
        """Who hears broadcasts of `cls` (about `subject`: those who hear the class about it too)."""
        return sorted(p.name for p in self._peers.values() if p.hears(cls, subject))

    # ----------------------------------------------------------------- conversations

    def _new_conv_id(self) -> str:
        self._conv_n += 1
        return f"{self._conv_prefix}{self._conv_n}"

    async def start(self, cls: str, *messages: Message, to: str | None = None, heard_by: Names = ()) -> Conversation:
        """Open a conversation and send its first batch: to one module, or to the listeners of cls, among
        them `heard_by`, listeners this bus does not track that must acknowledge it (docs/protocol.md)."""
        return self._start(cls, messages, to, heard_by)

    def _start(self, cls: str, messages: tuple[Message, ...], to: str | None, heard_by: Names = ()) -> Conversation:
        """start() without its coroutine (request() calls it on every round trip)."""
        spec = catalogue.CONVERSATION_CLASSES.get(cls)
        if spec is None:
            raise MessageError(f"unknown conversation class {cls!r}")
        conv = Conversation(self, self._new_conv_id(), spec.name, self.name)  # a str, not a Conv member
        conv.peer = to
        self._convs[conv.id] = conv
        try:
            conv.sent = self.send_batch(conv, messages, to, heard_by)  # conv.send() without its coroutine
        except BaseException:
            conv.end()
            raise
        return conv

    async def request(
        self, cls: str, *messages: Message, to: str | None = None, timeout: float | None = None
    ) -> tuple[Conversation, Batch]:
        """Open a conversation and wait for the first answer."""
        conv = self._start(cls, messages, to)
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
            conv = Conversation(self, conv_id, cls, initiator(conv_id) or peer)
            conv.peer = peer
            conv.sent = self.outbox.next_idx(conv_id)
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
                waiter = self.deadlines.waiter(timeout)
            self._incoming_waiters.append(waiter)
            try:
                conv = await waiter
            except TimeoutError:
                return None
            finally:
                self.deadlines.discard(waiter)
        if conv is CLOSED:
            self._incoming.appendleft(conv)
            return None
        return conv

    def accept(self, handler: Callable[[Conversation], None] | None) -> None:
        """Hand every conversation another module opens with us to `handler`, called at once on the bus's
        loop as its first batch is delivered (those already queued first), instead of queueing them for
        first_message(); None: queue them again. The handler must not block: it answers at once
        (Conversation.reply) or starts a task. No future, task or loop turn stands between the datagram and
        it: a module's conversations start a loop turn sooner, an answer given at once two sooner."""
        self._accept = handler
        while handler is not None and self._incoming and self._incoming[0] is not CLOSED:
            handler(self._incoming.popleft())

    def _put_incoming(self, conv: Conversation) -> None:
        """A new conversation: to accept()'s handler, or the longest-waiting first_message() still
        waiting, or queued."""
        if self._accept is not None and conv is not CLOSED:
            self._accept(conv)
            return
        waiters = self._incoming_waiters
        while waiters:
            waiter = waiters.popleft()
            if not waiter.done():
                waiter.set_result(conv)
                return
        self._incoming.append(conv)

    def end_conversation(self, conv: Conversation) -> None:
        """Route no more messages to `conv` (Conversation.end): later ones are acknowledged and dropped."""
        if self._convs.get(conv.id) is conv:
            del self._convs[conv.id]
        if conv.initiator != self.name:  # ours are known ended by their id (_is_ended): not remembered
            self._ended[conv.id] = None
            while len(self._ended) > MAX_REMEMBERED:
                self._ended.popitem(last=False)

    def _is_ended(self, conv_id: str) -> bool:
        """A conversation we took part in and ended, or one opened by us (now or in an earlier incarnation)."""
        return conv_id in self._ended or (conv_id.startswith(self._mine) and initiator(conv_id) == self.name)

    # ----------------------------------------------------------------- sending

    def send_batch(self, conv: Conversation, messages: tuple[Message, ...], to: str | None, also: Names = ()) -> int:
        """Number, encode (all or nothing), transmit and track one batch; returns the conversation's next idx."""
        if not messages:
            raise MessageError("a send needs at least one message")
        if not self._open or self.closed:
            raise BusError(f"{self.name} is not signed on to the bus")
        conv_id, cls = conv.id, conv.cls
        allowed = _ALLOWED[cls]
        for m in messages:  # fields were checked when message() built m; receivers check them again
            if m.name not in allowed:
                raise MessageError(f"message {m.name} does not belong to conversation {cls}")
        outbox = self.outbox
        out = outbox.outgoing(conv_id, conv.sent)
        start = out.next_idx
        base = out.unsettled[0][0] if out.unsettled else start
        acks: tuple[int, ...] | list[int] = ()
        to_inc = 0
        if to is not None:
            peer = self._peers.get(to)
            if peer is not None:
                due = outbox.take_acks((to, peer.inc))
                if due is not None:
                    acks, to_inc = due, peer.inc
        n = len(messages)
        seq = self._seq
        own, encode = self._origin, wire.encode_msg
        if also and to is None and self._members.older:  # a listener we do not track may read an older version
            version = self._members.version_for(also)
            if version != self._speaking:
                own = self._origin_in(version)
        subject = j = ""  # what the batch is about, where the kernel filter reads it (a class may name one)
        about = catalogue.SUBJECT_FIELDS.get(cls)
        if about is not None:
            subject = j = str(messages[0].fields.get(about) or "")
        ti = to_inc
        # Encode everything before sending anything: an oversize batch fails whole, at the sender.
        try:
            m = messages[0]  # the first message carries the batch's size and the acks
            datas = [encode(own, seq + 1, conv_id, cls, start, n - 1, 0, base, to, m.name, m.__dict__, j, acks, ti)]
            for i in range(1, n):
                m = messages[i]
                datas.append(encode(own, seq + 1 + i, conv_id, cls, start + i, 0, i, base, to, m.name, m.__dict__, j))
        except MessageError:
            if acks:
                outbox.give_back_acks((to, to_inc), acks)  # type: ignore[arg-type]
            raise
        self._seq = seq + n
        out.next_idx = start + n
        for data in datas:  # first on the wire; the bookkeeping below can wait that long
            self._transmit(data)
        if to is not None:
            outbox.track(datas, messages, {to}, out, start, seq, conv_id, cls, to, base, subject)
        else:
            peers = self._peers.values()  # (Peer.hears, inline: this runs once a broadcast for every peer)
            waiting = {p.name for p in peers if cls in p.interest or (subject in p.subjects.get(cls, ()))}
            waiting.update(also)
            if waiting:
                outbox.track(datas, messages, waiting, out, start, seq, conv_id, cls, to, base, subject)
            else:
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
        if not self._open:
            raise BusError(f"{self.name} is not signed on to the bus")
        try:
            self.transport.send(self.guard.seal(data))
        except (BlockingIOError, InterruptedError):
            self.stats["send_lost"] += 1
        except OSError as e:
            self.stats["send_lost"] += 1
            self.log.warning("bus send failed (%s): counted as lost", e)

    async def _beat(self) -> None:
        """Every heartbeat: read the beats that came, send ours, then look for who went silent."""
        while True:  # at the ticks of the host's clock: the host's modules wake together (membership.tick)
            await asyncio.sleep(tick(self.cfg.heartbeat))
            # Each step apart: whatever one of them meets (a bug, a datagram no check foresaw) must
            # not cost the others their turn, least of all our beat and the expiry of silent peers.
            run = self.faults.run
            run("reading beats", lambda: self._members.take_beats(heartbeat=True))
            run("sending our beat", self._members.send_beat)
            run("expiring peers", self._expire)
            run("refreshing keys", self.guard.refresh)
            for listener in self.beat_listeners:
                run("heartbeat listener", listener)

    def _expire(self) -> None:
        now = time.monotonic()
        self._members.expire(now)
        self._inbound.housekeep(now, self._convs)

    # ----------------------------------------------------------------- receiving

    def decode(self, data: bytes, what: str) -> Envelope | None:
        """The datagram's envelope; None (counted, logged) if it is malformed."""
        try:
            return wire.decode(data)
        except MessageError as e:
            self._malformed(data, what, e)
            return None

    def _malformed(self, data: bytes, what: str, e: MessageError) -> None:
        """Only a key holder gets here: counted and summarised like the rest."""
        self.stats["malformed"] += 1
        self.guard.drops.drop("malformed", self.transport.source)
        self.log.debug("dropped malformed %s (%d bytes): %s", what, len(data), e)

    def _handle(self, data: bytes) -> None:
        try:  # no datagram, and no bug, takes the receive path down, nor writes a traceback per datagram
            opened = self.guard.open(data, False, self.transport.source)
            if opened is None:
                return
            try:  # (not through decode: one call less a datagram)
                env = wire.decode(opened[0])
            except MessageError as e:
                self._malformed(opened[0], "datagram", e)
                return
            if env.inc == self.inc and env.src == self.name:
                return
            if opened[1] and env.kind == "msg" and env.cls not in catalogue.LOT_CLASSES:
                self._refuse(env)
                return
            now = time.monotonic()
            peer = self._peers.get(env.src)
            if peer is not None and peer.inc == env.inc:
                peer.last_seen = now  # any datagram proves life, not only hellos
            elif env.version != self._speaking or env.version != wire.VERSION:
                self._members.heard_version(env, now)  # a sender we hold no hello of, in another version
            kind = env.kind
            self.stats[kind] += 1  # datagrams read, by kind: what the kernel filter let through
            if kind == "msg":
                self._on_msg(env, now)
            elif kind == "ack":
                self._on_ack(env)
            elif kind == "hello":
                self._members.on_hello(env, peer)
            elif peer is not None and peer.inc == env.inc:
                self._members.left(env.src, "said bye", clean=True)
        except Exception as e:
            self.faults.failed("handling a datagram", e)

    def _refuse(self, env: Envelope) -> None:
        """A msg a lot script may not send: acknowledged (so it is not sent again), answered Not_Auth
        by the module it was for, counted, and logged once per source and interval."""
        to = env.to
        if to is not None and to != self.name:
            return
        if to is None and env.cls not in self._interest and env.subject not in self._subjects.get(env.cls, ()):
            return
        self.guard.drops.drop("not_authorized", f"{env.src} ({env.cls})")
        key = (env.src, env.inc)
        self.outbox.ack(key, env.seq)
        if to is None or env.idx or self._inbound.duplicate(key, env.seq, time.monotonic()):
            return
        answer = catalogue.refusal(env.cls, AckCode.NOT_AUTH, "not allowed under the lot key", env.fields)
        if answer is not None:
            conv = self.resume(env.conv, env.cls, env.src)
            self.send_batch(conv, (answer,), env.src)
            conv.end()

    def _on_ack(self, env: Envelope) -> None:
        if env.to != self.name or env.to_inc != self.inc:
            return
        self.outbox.acked(env.src, env.acks)

    def _on_msg(self, env: Envelope, now: float) -> None:
        to, src, inc = env.to, env.src, env.inc
        if to is not None and to != self.name:
            return
        conv_id, cls = env.conv, env.cls
        conv = self._convs.get(conv_id)
        subjects = self._subjects
        if conv is None and to is None and cls not in self._interest and env.subject not in subjects.get(cls, ()):
            return  # not for us (nor about a subject we hear it about): no ack, the sender does not count us
        seq = env.seq
        key = (src, inc)
        self.outbox.ack(key, seq)
        try:
            if self._inbound.duplicate(key, seq, now):
                self.stats["duplicates"] += 1
            elif conv is None and self._is_ended(conv_id):
                self.stats["late"] += 1
                self.log.warning(
                    "late %s from %s in ended conversation: dropped", env.msg, src, extra={"conv": f"{conv_id} {cls}"}
                )
            else:
                name = env.msg
                mc = _MEMBERS.get((cls, name))
                msg: Message | None
                try:
                    if mc is None:
                        msg = catalogue.check(cls, name, env.fields)  # raises, saying what is wrong
                    else:
                        mc.check(env.fields)
                        msg = Message(name, env.fields)
                except MessageError as e:
                    # Still take its place in the order, so the messages after it are not held up forever.
                    self.stats["invalid"] += 1
                    self.log.warning("dropped invalid %s from %s: %s", name, src, e, extra={"conv": f"{conv_id} {cls}"})
                    msg = None
                if msg is not None and self._inbound.in_order(env, now):
                    # The fast path: one message, next in its stream, nothing waiting (order.Inbound.in_order).
                    self.stats["delivered"] += 1
                    if conv is not None:
                        conv.deliver(Batch(src, (msg,)))
                    else:
                        self._open_conversation(env, Batch(src, (msg,)))
                else:
                    self._inbound.place(env, msg, now)
        finally:
            # Acks riding on the msg are taken after it is delivered (even if a handler failed): an
            # answer given at once (Bus.accept) leaves sooner, and a base computed before them is only
            # lower, never wrong.
            if env.acks and to is not None and env.to_inc == self.inc:
                self.outbox.acked(src, env.acks)

    def _deliver(self, head: Envelope, msgs: tuple[Message | None, ...]) -> None:
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
        conv = self._convs.get(head.conv)
        if conv is not None:
            conv.deliver(batch)
            return
        if head.to is None and head.cls not in self._interest and head.subject not in self._subjects.get(head.cls, ()):
            return
        self._open_conversation(head, batch)

    def _open_conversation(self, head: Envelope, batch: Batch) -> None:
        """A batch for no conversation held here: the opening of a new one (else a stray, dropped)."""
        if head.msg != _OPENERS[head.cls]:
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
