"""BlockingBus: a Bus running in its own thread, for code that is not asyncio (lot scripts, the Human
Interface, tests). Every method is the Bus's own coroutine run on that thread's loop.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Coroutine, Iterable, Mapping
from typing import Any, TypeVar

from gwc.config import BusConfig
from gwc.ipc import eventloop
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import Message
from gwc.ipc.conversation import DEFAULT, Batch, Conversation, Peer
from gwc.ipc.transport import Transport

T = TypeVar("T")


class BlockingBus:
    """A Bus running in its own thread, for code that is not asyncio (lot scripts, the HI, tests).

    Every method is the Bus's own coroutine run on that thread's loop; nothing is reimplemented.
    """

    def __init__(
        self,
        name: str,
        cfg: BusConfig,
        log: logging.Logger,
        interest: Iterable[str] = (),
        transport: Transport | None = None,
        ignored_peers: tuple[str, ...] = (),
    ) -> None:
        self._loop = eventloop.new_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name=f"bus-{name}", daemon=True)
        self._thread.start()
        self.bus: Bus = self.run(self._make(name, cfg, log, interest, transport, ignored_peers))
        self._closed = False

    @staticmethod
    async def _make(
        name: str,
        cfg: BusConfig,
        log: logging.Logger,
        interest: Iterable[str],
        transport: Transport | None,
        ignored_peers: tuple[str, ...],
    ) -> Bus:
        bus = Bus(name, cfg, log, interest, transport, ignored_peers)
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

    def request_soon(
        self, cls: str, *messages: Message, to: str | None = None, timeout: float | None = None
    ) -> Callable[[], tuple[BlockingConversation, Batch]]:
        """request() in two halves: returns once the request is on the wire, with a function that
        waits for the answer, so that the caller can work meanwhile (work begun before the send would
        hold the GIL while this bus's thread sends). The caller ends the conversation as after request()."""
        conv = self.run(self.bus.start(cls, *messages, to=to))
        answer = asyncio.run_coroutine_threadsafe(conv.next_message(timeout), self._loop)

        def answered() -> tuple[BlockingConversation, Batch]:
            try:
                batch = answer.result()
            except BaseException:
                self.call_soon(conv.end)
                raise
            return BlockingConversation(self, conv), batch

        return answered

    def resume(self, conv_id: str, cls: str, peer: str) -> BlockingConversation:
        async def _resume() -> Conversation:
            return self.bus.resume(conv_id, cls, peer)

        return BlockingConversation(self, self.run(_resume()))

    def first_message(self, timeout: float | None = None) -> BlockingConversation | None:
        conv = self.run(self.bus.first_message(timeout))
        return BlockingConversation(self, conv) if conv else None

    def in_bus_thread(self) -> bool:
        """Whether the caller runs on the bus's own thread (where `run` would wait for itself forever)."""
        return threading.current_thread() is self._thread

    def call(self, fn: Callable[[], T]) -> T:
        """fn() on the bus thread (where the Bus may be used directly); returns its result."""

        async def _call() -> T:
            return fn()

        return self.run(_call())

    def set_interest(self, classes: Iterable[str], subjects: Mapping[str, Iterable[str]] | None = None) -> None:
        """Change the interest filter; returns once it applies (unknown classes raise here)."""
        classes = list(classes)

        async def _set() -> None:
            self.bus.set_interest(classes, subjects=subjects)

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

    def send(self, *messages: Message, to: str | None = DEFAULT) -> None:
        self._owner.run(self.conv.send(*messages, to=to))

    def next_message(self, timeout: float | None = None) -> Batch:
        return self._owner.run(self.conv.next_message(timeout))

    def expect(self, *names: str, timeout: float | None = None) -> Batch:
        return self._owner.run(self.conv.expect(*names, timeout=timeout))

    def end(self) -> None:
        self._owner.call_soon(self.conv.end)
