"""The bus's receiving side below the conversations: which msgs were seen (dedup), and each
sender's messages per conversation put back in order, batches assembled whole (docs/protocol.md).
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Container

from gwc.config import BusConfig
from gwc.ipc.catalogue import Message
from gwc.ipc.wire import Envelope

Deliver = Callable[[Envelope, tuple[Message | None, ...]], None]
StreamKey = tuple[str, str, int]  # (conversation, sender, sender's incarnation)


class Stream:
    """Per (conversation, sender, incarnation): reorder buffer and the batch being assembled."""

    __slots__ = ("batch", "buffer", "gap_since", "next_idx", "touched")

    def __init__(self, next_idx: int, touched: float) -> None:
        self.next_idx = next_idx
        self.buffer: dict[int, tuple[Envelope, Message | None]] | None = None  # made when a message comes early
        self.batch: list[tuple[Envelope, Message | None]] | None = None  # made when a batch of several begins
        self.touched = touched
        self.gap_since = 0.0  # when the buffer last became non-empty (a message is missing)


class Seen:
    """The seqs taken from one (sender, incarnation), for dedup: two generations, swapped every
    2 x retry_deadline by the housekeeping, so each seq is remembered that long at least (and at
    most twice that) for the price of two set lookups per msg."""

    __slots__ = ("new", "old", "since")

    def __init__(self, since: float) -> None:
        self.new: set[int] = set()
        self.old: set[int] = set()
        self.since = since


class Inbound:
    """Dedup and order for one bus; complete batches go to `deliver` (the conversation layer)."""

    def __init__(self, cfg: BusConfig, log: logging.Logger, stats: collections.Counter[str], deliver: Deliver) -> None:
        self.cfg = cfg
        self.log = log
        self.stats = stats
        self.deliver = deliver
        self.seen: dict[tuple[str, int], Seen] = {}
        # Oldest-touched first, so housekeeping looks only at streams old enough to forget.
        self.streams: collections.OrderedDict[StreamKey, Stream] = collections.OrderedDict()
        self.gaps: dict[StreamKey, Stream] = {}  # streams holding messages that came early

    def duplicate(self, key: tuple[str, int], seq: int, now: float) -> bool:
        """Whether (sender, inc) already sent seq (within memory); remembers it if not."""
        seen = self.seen.get(key)
        if seen is None:
            seen = self.seen[key] = Seen(now)
        elif seq in seen.new or seq in seen.old:
            return True
        seen.new.add(seq)
        return False

    def in_order(self, env: Envelope, now: float) -> bool:
        """The fast path (docs/performance.md, "The bus"): whether the new msg is a one-message batch that
        is next in its stream with nothing waiting before or around it; if so it takes its place here and
        the caller delivers it at once. Otherwise nothing changes: place() it."""
        if env.more or env.part:
            return False
        skey = (env.conv, env.src, env.inc)
        streams = self.streams
        st = streams.get(skey)
        if st is None:
            if env.idx != env.base:
                return False
            # No state for this stream (first contact, or we restarted): what is below base is settled.
            streams[skey] = Stream(env.idx + 1, now)
            return True
        if env.idx != st.next_idx or st.buffer or st.batch:
            return False
        st.next_idx += 1
        st.touched = now
        streams.move_to_end(skey)
        return True

    def place(self, env: Envelope, msg: Message | None, now: float) -> None:
        """A new msg (msg None: invalid, still holding its place): deliver what it completes."""
        conv_id, src, inc = env.conv, env.src, env.inc
        skey = (conv_id, src, inc)
        streams = self.streams
        st = streams.get(skey)
        if st is None:
            # No state for this stream (first contact, or we restarted): what is below base is settled.
            st = streams[skey] = Stream(env.base, now)
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
            self.deliver(env, (msg,))
            return
        buffer = st.buffer
        if not buffer:
            st.gap_since = now
            self.gaps[skey] = st
            if buffer is None:
                buffer = st.buffer = {}
        buffer[idx] = (env, msg)
        self.advance(st, skey, upto=env.base)

    def advance(self, st: Stream, skey: tuple[str, str, int], upto: int = 0) -> None:
        """Deliver what is in order; a message missing below `upto` is settled elsewhere: skip it."""
        lost = 0
        if st.buffer is None:
            st.buffer = {}
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
                self.deliver(head, tuple(m for _, m in batch))
        if not st.buffer:
            self.gaps.pop(skey, None)
        if lost:
            self.stats["gaps"] += 1
            self.log.warning(
                "%d message(s) from %s never arrived (the sender gave up on them); going on",
                lost,
                skey[1],
                extra={"conv": skey[0]},
            )

    def housekeep(self, now: float, live: Container[str]) -> None:
        """Forget old seqs and idle streams (not those of `live` conversations); give up on old gaps."""
        # A sender retransmits for at most retry_deadline after the first send: twice that is safe.
        remember = 2 * self.cfg.retry_deadline
        horizon = now - remember
        for sender, seen in list(self.seen.items()):
            if seen.since <= horizon:
                if not seen.new and not seen.old:
                    del self.seen[sender]
                    continue
                seen.old, seen.new, seen.since = seen.new, set(), now
        for key, st in list(self.gaps.items()):
            if now - st.gap_since > self.cfg.retry_deadline + self.cfg.heartbeat:
                # The sender has given up on what is missing: deliver what came after it.
                self.advance(st, key, upto=min(st.buffer or (st.next_idx,)))
        streams = self.streams
        while streams:
            key, st = next(iter(streams.items()))
            if st.touched >= horizon:
                break
            if st.buffer or key[0] in live:
                st.touched = now  # kept: looked at again `remember` from now
                streams.move_to_end(key)
            else:
                del streams[key]
