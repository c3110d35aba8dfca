"""The WC's end of the queue pair, for an asyncio program: one request at a time, answers by seq.

On Linux a POSIX queue descriptor is a file the event loop can watch, so the ME's queue is read
by the WC's own event loop (no reader thread, no hand-over between threads). There, an answer
whose seq is the pending request's completes that request; a late answer to an earlier request
(after its timeout) is dropped, never taken for the answer to the next one; what the ME sends on
its own (CELL_ALAR, RUN_COMPL) goes to `on_unsolicited`.
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Callable

from gwc.errors import GwcError, QueueError, QueueFull, QueueTimeout
from gwc.ipc.mq import Channel, MeMessage, MessageId

UNSOLICITED = (MessageId.CELL_ALAR, MessageId.RUN_COMPL, MessageId.ME_LOST, MessageId.ME_BACK)
# How long a request waits for its answer right where it was sent, before the event loop watches the
# queue for it. A ready ME answers a ping in tens of microseconds: caught here, the answer costs no
# turn of the loop (an asyncio round trip cost 2-4x the bare queue's, mostly waking the loop through
# epoll and running a task step). The loop stays blocked at most this long; slower answers (a run's
# setup on a real machine) come through the loop as before.
QUICK_S = 0.0005


class MeDied(GwcError):
    """The ME did not answer in time, or its queue stayed full: it is not reading."""


class MeLink:
    def __init__(
        self, channel: Channel, log: logging.Logger, on_unsolicited: Callable[[MeMessage], None] = lambda msg: None
    ) -> None:
        self.channel = channel
        self.log = log
        self.on_unsolicited = on_unsolicited
        self.heard = time.monotonic()  # when the ME was last heard from
        self._lock = asyncio.Lock()
        self._seq = random.randrange(1, 2**31)  # a restarted WC never takes an old answer for a new one
        self._pending: tuple[int, asyncio.Future[MeMessage]] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fd: int | None = None

    @property
    def busy(self) -> bool:
        """A request is out (or waiting its turn)."""
        return self._lock.locked()

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Open the queues and read the ME's from `loop` (call in the loop's thread)."""
        self.channel.open()
        self._loop = loop
        self._fd = self.channel.fileno()
        loop.add_reader(self._fd, self._readable)
        self._readable()  # what the ME sent before we watched

    def stop(self) -> None:
        """Stop reading and close our end (the queues stay). Safe to call twice."""
        if self._loop is not None and self._fd is not None and not self._loop.is_closed():
            self._loop.remove_reader(self._fd)
        self._fd = None
        self.channel.close()

    def _readable(self) -> None:
        while True:
            try:
                msg = self.channel.poll()
            except QueueError as e:
                self.log.warning("garbled record from the ME dropped: %s", e)
                continue
            if msg is None:
                return
            self._arrived(msg)

    def _arrived(self, msg: MeMessage) -> None:
        self.heard = time.monotonic()
        if msg.message_id in UNSOLICITED:
            self.on_unsolicited(msg)
        elif self._pending is not None and self._pending[0] == msg.seq and not self._pending[1].done():
            self._pending[1].set_result(msg)
        else:
            self.log.warning("stale or unexpected answer from the ME dropped: %s", msg.describe())

    def send(self, msg: MeMessage) -> None:
        """Send without waiting for an answer (ME_START_WAIT has none)."""
        self.channel.send(msg)

    async def request(self, msg: MeMessage, timeout: float, hold_open: Callable[[], bool] = lambda: False) -> MeMessage:
        """Send one request and wait for its answer, one request at a time as Listing 3 did.

        MeDied if no answer comes within `timeout` (for as long as `hold_open()` is true the wait goes
        on: an operator alarm may hold the ME up) or the ME's queue is full; QueueError if the
        request cannot be sent at all (a field too long).
        """
        loop = self._loop
        assert loop is not None, "MeLink.start() first"
        async with self._lock:
            self._seq = self._seq % (2**32 - 1) + 1
            req = msg.with_seq(self._seq)
            try:
                try:
                    self.channel.send(req)
                except QueueFull as e:
                    raise MeDied(str(e)) from e
                quick = self._quick(req.seq)
                if quick is not None:
                    return quick
                while True:
                    # The answer's own future with a timer on it: cheaper than asyncio.wait per request.
                    answer: asyncio.Future[MeMessage] = loop.create_future()
                    self._pending = (req.seq, answer)
                    timer = loop.call_later(timeout, _expire, answer)
                    try:
                        return await answer
                    except _Expired:
                        if not hold_open():
                            self._withdraw()
                            raise MeDied(f"ME did not answer {msg.message_id.name} within {timeout:.1f}s") from None
                    finally:
                        timer.cancel()
            finally:
                self._pending = None

    def _quick(self, seq: int) -> MeMessage | None:
        """The answer to request `seq` if it comes within QUICK_S (what else comes meanwhile is handled
        as the loop would handle it), else None."""
        deadline = time.monotonic() + QUICK_S
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = self.channel.receive(left)
            except QueueTimeout:
                return None
            except QueueError as e:
                self.log.warning("garbled record from the ME dropped: %s", e)
                continue
            if msg.seq == seq and msg.message_id not in UNSOLICITED:
                self.heard = time.monotonic()
                return msg
            self._arrived(msg)
        return None

    def _withdraw(self) -> None:
        """A request the ME did not read is taken back: the next ME would serve it out of its time (an old
        ME_START raising a second homing alarm)."""
        try:
            taken = self.channel.withdraw()
        except QueueError as e:
            self.log.warning("could not take back what the ME did not read: %s", e)
            return
        for old in taken:
            self.log.warning("the ME did not read %s: taken back from its queue", old.describe())


class _Expired(Exception):
    """A request's deadline passed (internal to MeLink.request)."""


def _expire(answer: asyncio.Future[MeMessage]) -> None:
    if not answer.done():
        answer.set_exception(_Expired())
