"""An in-memory transport: the buses of one process joined without sockets, for fast unit tests.

Buses whose configurations name the same group and port share one hub, as they would share the
multicast group. A datagram is handed to every other member on its own event loop, soon (never
inside the sender's call, as a socket would not either); beats wait in each member's box until its
heartbeat reads them. Nothing is lost or reordered unless the fault injector says so, exactly as on
loopback multicast.
"""

from __future__ import annotations

import asyncio
import collections
import threading
from collections.abc import Iterator

from gwc.config import BusConfig
from gwc.errors import BusError
from gwc.ipc.transport import Handler, Transport

MAX_BEATS = 4096  # beats kept unread per member, like a socket's receive buffer
_HUBS: dict[tuple[str, int], list[MemoryTransport]] = {}
_LOCK = threading.Lock()  # BlockingBus members live on threads of their own


class MemoryTransport(Transport):
    source = "memory"

    def __init__(self, cfg: BusConfig) -> None:
        self._key = (cfg.group, cfg.port)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._handler: Handler | None = None
        self._own = b""
        self._beats: collections.deque[bytes] = collections.deque(maxlen=MAX_BEATS)

    async def open(self, loop: asyncio.AbstractEventLoop, own: bytes, on_datagram: Handler) -> None:
        self._loop, self._own, self._handler = loop, own, on_datagram
        with _LOCK:
            _HUBS.setdefault(self._key, []).append(self)

    def _members(self) -> list[MemoryTransport]:
        if self._handler is None:
            raise BusError("the bus transport is not open")
        with _LOCK:
            return list(_HUBS.get(self._key, ()))

    def send(self, data: bytes) -> None:
        for m in self._members():
            if m is not self and m._handler is not None and not data.startswith(m._own):
                m._deliver(data)

    def _deliver(self, data: bytes) -> None:
        loop, handle = self._loop, self._handler
        if loop is None or handle is None or loop.is_closed():
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            loop.call_soon(handle, data)
        else:
            loop.call_soon_threadsafe(handle, data)

    def send_beat(self, data: bytes) -> None:
        for m in self._members():
            if m is not self and not data.startswith(m._own):
                m._beats.append(data)

    def beats(self) -> Iterator[bytes]:
        while self._beats:
            yield self._beats.popleft()

    def close(self) -> None:
        if self._handler is None:
            return
        self._handler = None
        with _LOCK:
            members = _HUBS.get(self._key, [])
            if self in members:
                members.remove(self)
            if not members:
                _HUBS.pop(self._key, None)
