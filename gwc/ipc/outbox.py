"""The bus's outbox: what one module sent and what it owes (see gwc/ipc/bus.py for the rules).

* Acknowledgements due: gathered per peer (name, incarnation) and sent together a quarter of an
  `ack_timeout` later, unless they ride on the next msg to that peer first (`take_acks`).
* Msgs not yet acknowledged by every module they are meant for: retransmitted with exponential
  backoff until acknowledged or `retry_deadline` passes; one timer for all of them.
* Each conversation's numbering (`Outgoing`): the next idx, and the batches not yet settled, which
  make the `base` a receiver reads to tell settled from missing.

The bus numbers, encodes and transmits a batch, then hands it here (`track`); datagrams come back
to the bus's `transmit` for every retransmission and ack datagram. Nothing here waits for the
application: it all runs on the bus's event loop.
"""

from __future__ import annotations

import asyncio
import collections
import heapq
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import replace

from gwc.config import BusConfig
from gwc.errors import BusError
from gwc.ipc import wire
from gwc.ipc.catalogue import Message
from gwc.ipc.conversation import INF, Outgoing, Peer, Pending
from gwc.ipc.wire import Envelope

MAX_RTO = 0.5  # retransmission backoff stops growing here
MAX_PIGGYBACK = 32  # acks riding on a msg at most; the rest go in ack datagrams
MAX_REMEMBERED = 65_536  # conversations whose numbering is remembered, newest first
MAX_ACKS = 1000  # seqs in one ack datagram


class Outbox:
    """Acknowledgement and retransmission for one bus (see the module docstring)."""

    def __init__(
        self,
        name: str,
        inc: int,
        cfg: BusConfig,
        log: logging.Logger,
        stats: collections.Counter[str],
        transmit: Callable[[bytes], None],
    ) -> None:
        self.name = name
        self.inc = inc
        self.cfg = cfg
        self.log = log
        self.stats = stats
        self.transmit = transmit  # seal and send one datagram (the bus's); raises BusError once closed
        self.version = wire.VERSION  # the wire version acks, hellos and byes go in (Bus.speak sets it)
        self.loop: asyncio.AbstractEventLoop | None = None  # set when the bus signs on
        self.pending: dict[int, Pending] = {}  # seq -> a msg not yet acknowledged by all it is meant for
        self.acks_due: dict[tuple[str, int], list[int]] = {}  # (peer, inc) -> seqs to acknowledge
        self._out: collections.OrderedDict[str, Outgoing] = collections.OrderedDict()
        # One timer for all pending msgs. First sends are due in send order (a deque); retransmissions,
        # with their backoff, in a heap. Entries of msgs acked since are skipped.
        self._due_first: collections.deque[tuple[float, int]] = collections.deque()
        self._due_again: list[tuple[float, int]] = []
        self._rtx_timer: asyncio.TimerHandle | None = None
        self._rtx_at = INF
        self._ack_timer: asyncio.Handle | None = None  # the ack timer, then the flush it put last in the turn
        self._flushed: asyncio.Future[None] | None = None  # drain() waiting for the last acks

    # ----------------------------------------------------------------- numbering

    def outgoing(self, conv_id: str, next_idx: int) -> Outgoing:
        """The conversation's numbering, made (from `next_idx`) if this is its first send we remember."""
        outs = self._out
        out = outs.get(conv_id)
        if out is None:
            out = outs[conv_id] = Outgoing(next_idx)
            if len(outs) > MAX_REMEMBERED:
                outs.popitem(last=False)
        else:
            outs.move_to_end(conv_id)
        return out

    def next_idx(self, conv_id: str) -> int:
        """The idx our next msg in the conversation takes (0 if we sent nothing in it that we remember)."""
        out = self._out.get(conv_id)
        return out.next_idx if out else 0

    # ----------------------------------------------------------------- acknowledging what we receive

    def ack(self, key: tuple[str, int], seq: int) -> None:
        """Acknowledge soon: acks due to one peer (name, inc) go out together, or ride on our next msg to it."""
        due = self.acks_due.get(key)
        if due is None:
            self.acks_due[key] = [seq]
        else:
            due.append(seq)
        if self._ack_timer is None and self.loop is not None:
            self._ack_timer = self.loop.call_later(self.cfg.ack_timeout / 4, self._acks_due)

    def _acks_due(self) -> None:
        """The ack timer: flush at the end of this loop turn, not now. The timer runs before the turn's
        ready callbacks, among them often a task woken by the very msg whose ack is due, which is about
        to answer it: its answer takes the ack along (take_acks) and no ack datagram goes."""
        assert self.loop is not None
        self._ack_timer = self.loop.call_soon(self.flush_acks)

    def take_acks(self, key: tuple[str, int]) -> list[int] | None:
        """The acks due to a peer, taken to ride on a msg to it; None if none, or too many to ride."""
        due = self.acks_due.get(key)
        if due and len(due) <= MAX_PIGGYBACK:  # more wait for their own ack datagram
            del self.acks_due[key]
            return due
        return None

    def give_back_acks(self, key: tuple[str, int], acks: Iterable[int]) -> None:
        """Acks taken to ride on a msg that was never sent: due again."""
        self.acks_due.setdefault(key, []).extend(acks)

    def flush_acks(self) -> None:
        """Send every ack due now, one datagram per peer (more if many)."""
        self._ack_timer = None
        due, self.acks_due = self.acks_due, {}
        for (src, inc), seqs in due.items():
            for i in range(0, len(seqs), MAX_ACKS):
                acks = tuple(seqs[i : i + MAX_ACKS])
                self.send_envelope(Envelope(kind="ack", src=self.name, inc=self.inc, to=src, to_inc=inc, acks=acks))

    def send_envelope(self, env: Envelope) -> None:
        """Encode and send a datagram that is not a msg (an ack, a hello, a bye); lost if the bus closed."""
        if env.version == wire.VERSION:  # (a sign-on query names its own: the oldest version we speak)
            env.version = self.version  # the version the bus speaks (Bus.speak)
        try:
            self.transmit(wire.encode(env))
        except BusError as e:  # not signed on (closing): lost like a dropped datagram
            self.log.warning("send of %s failed: %s", env.kind, e)

    # ----------------------------------------------------------------- what we sent, until acknowledged

    def track(
        self,
        datas: list[bytes],
        messages: tuple[Message, ...],
        waiting: set[str],
        out: Outgoing,
        start: int,
        seq: int,
        conv_id: str,
        cls: str,
        to: str | None,
        base: int,
        subject: str,
    ) -> None:
        """Wait for `waiting` to acknowledge a batch just transmitted (its first seq is seq + 1)."""
        n = len(datas)
        batch = [start, n]
        if out.unsettled is None:
            out.unsettled = [batch]
        else:
            out.unsettled.append(batch)
        now = time.monotonic()
        rto = self.cfg.ack_timeout
        due = now + rto
        pending = self.pending
        if n == 1:  # the usual batch: one message
            pending[seq + 1] = Pending(
                datas[0], waiting, now, rto, batch, conv_id, cls, messages[0].name, to, base, subject
            )
            self._due_first.append((due, seq + 1))
        else:
            first_due = self._due_first
            for i, data in enumerate(datas):
                seq += 1
                w = set(waiting) if i else waiting
                pending[seq] = Pending(data, w, now, rto, batch, conv_id, cls, messages[i].name, to, base, subject)
                first_due.append((due, seq))
        if self._rtx_timer is None or due < self._rtx_at:
            self._arm_retransmit(due)

    def acked(self, src: str, seqs: Iterable[int]) -> None:
        """`src` acknowledged these seqs."""
        pending = self.pending
        for seq in seqs:
            p = pending.get(seq)
            if p is not None:
                p.waiting.discard(src)
                if not p.waiting:
                    self._done(seq)

    def forget_waiting(self, name: str, directed_too: bool, unless: Peer | None = None) -> None:
        """Stop waiting for acks from `name` (broadcasts; directed sends too when it left for good), or,
        given `unless` (its new interest), for its acks of the broadcasts it no longer hears."""
        for seq, p in list(self.pending.items()):
            if name not in p.waiting or (p.to is not None and not directed_too):
                continue
            if unless is not None and (p.to is not None or unless.hears(p.cls, p.subject)):
                continue
            p.waiting.discard(name)
            if not p.waiting:
                self._done(seq)

    async def drain(self, timeout: float) -> None:
        """Wait up to `timeout` s until every msg sent is acknowledged (warned about if not)."""
        if not timeout or not self.pending or self.loop is None:
            return
        self._flushed = self.loop.create_future()
        try:
            await asyncio.wait_for(self._flushed, timeout)
        except TimeoutError:
            self.log.warning("closing with %d datagram(s) unacknowledged", len(self.pending))

    def close(self) -> None:
        """Stop every timer and forget what is still unacknowledged."""
        for timer in (self._ack_timer, self._rtx_timer):
            if timer is not None:
                timer.cancel()
        self.pending.clear()

    # ----------------------------------------------------------------- retransmission

    def _arm_retransmit(self, when: float) -> None:
        """(Re)arm the one retransmission timer for `when` (monotonic time)."""
        if self._rtx_timer is not None:
            self._rtx_timer.cancel()
        assert self.loop is not None
        self._rtx_at = when
        self._rtx_timer = self.loop.call_later(when - time.monotonic(), self._retransmit_due)

    def _retransmit_due(self) -> None:
        """The retransmission timer: resend every msg due and not yet acked, then re-arm for the next.

        Runs at most every ack_timeout/4, so a retransmission may come that much after its due time;
        between runs, acked msgs cost nothing but their entry, skipped here.
        """
        self._rtx_timer = None
        now = time.monotonic()
        pending, first, again = self.pending, self._due_first, self._due_again
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
        p = self.pending[seq]
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
        self.transmit(p.data)
        p.rto = min(p.rto * 2, MAX_RTO)
        heapq.heappush(self._due_again, (now + p.rto, seq))

    def _done(self, seq: int) -> None:
        p = self.pending.pop(seq, None)
        if p is None:
            return
        batch = p.batch
        batch[1] -= 1
        if not batch[1]:
            out = self._out.get(p.conv)
            if out is not None and out.unsettled:
                unsettled = out.unsettled
                while unsettled and not unsettled[0][1]:
                    del unsettled[0]
                if not unsettled:
                    out.unsettled = None
        if not self.pending and self._flushed is not None and not self._flushed.done():
            self._flushed.set_result(None)
