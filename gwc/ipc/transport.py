"""The bus's transport: what moves datagrams between the modules of one bus, below the conversations.

A transport has two channels, as the bus has two ports: the bus channel (msgs, acks, sign-on hellos,
byes), whose datagrams are handed to the bus as they come, and the beat channel (periodic hellos),
read only when the bus asks, once a heartbeat. It may drop what the module would drop unread
(`set_filter`); the bus checks every datagram again. It never reorders, retransmits or interprets:
that is the conversation layer's work (gwc/ipc/bus.py), the same over every transport.

`UdpTransport` is the cell's: UDP multicast on loopback or a LAN, with a kernel socket filter.
`MemoryTransport` (gwc/ipc/memory.py) joins buses of one process, for fast unit tests.
"""

from __future__ import annotations

import asyncio
import ctypes
import logging
import random
import socket
import struct
import sys
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

from gwc.config import BusConfig, Faults
from gwc.errors import BusError
from gwc.ipc import wire

RCVBUF = 4 * 1024 * 1024
IP_MULTICAST_ALL = 49  # Linux's value, for Pythons whose socket module does not name it
SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)  # Linux's value

Handler = Callable[[bytes], None]


class Transport(ABC):
    """Datagrams to and from every module of one bus (see the module docstring)."""

    source: Any = None  # where the datagram being handled came from (an address), for drop reports

    @abstractmethod
    async def open(self, loop: asyncio.AbstractEventLoop, own: bytes, on_datagram: Handler) -> None:
        """Join; from now on every bus-channel datagram not beginning with `own` (this module's
        wire.Origin prefix) is passed to on_datagram, on `loop`."""

    @abstractmethod
    def send(self, data: bytes) -> None:
        """Send on the bus channel. Raises BlockingIOError when the medium is full (lost, like a
        dropped datagram) and BusError when not open."""

    @abstractmethod
    def send_beat(self, data: bytes) -> None:
        """Send on the beat channel (same losses as send)."""

    @abstractmethod
    def beats(self) -> Iterator[bytes]:
        """The beat-channel datagrams that came since the last call, our own skipped."""

    def set_filter(  # noqa: B027
        self,
        src: str,
        inc: int,
        interest: Iterable[str],
        ignored: tuple[str, ...] = (),
        subjects: Mapping[str, Iterable[str]] | None = None,
    ) -> None:
        """Drop before the module wakes what module `src` would drop unread, the hellos and byes of modules
        whose names begin with one of `ignored` among them, and the broadcasts of a class in `subjects`
        about other subjects (a hint; none by default)."""

    def ignore_beats_from(self, prefixes: tuple[str, ...]) -> None:  # noqa: B027  (optional)
        """Drop before the module reads them the beats of modules whose names begin with one of
        `prefixes` (none if there is none; a hint: the bus ignores them itself)."""

    def follow_beats(self, on_beats: Callable[[], None] | None) -> None:  # noqa: B027  (optional)
        """Call on_beats whenever beats are waiting (None: stop); for a transport a flood can fill."""

    @abstractmethod
    def close(self) -> None:
        """Leave. Safe to call twice."""


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
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("B", cfg.ttl))
        if sys.platform.startswith("linux"):
            # Only the groups this socket joined: without it Linux hands us every group joined on the
            # host at this port, and two cells on one port but different groups would hear each other.
            sock.setsockopt(socket.IPPROTO_IP, getattr(socket, "IP_MULTICAST_ALL", IP_MULTICAST_ALL), 0)
        sock.setblocking(False)
    except OSError as e:
        sock.close()
        raise BusError(f"cannot join bus group {cfg.group}:{port} on {cfg.interface}: {e}") from e
    return sock


class UdpTransport(Transport):
    """UDP multicast: the bus port for conversations, the next port for beats (docs/protocol.md)."""

    def __init__(self, cfg: BusConfig, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        self.kernel_filter = cfg.kernel_filter
        self._dest = (cfg.group, cfg.port)
        self._beat_dest = (cfg.group, cfg.beat_port)
        self._sock: socket.socket | None = None
        self._beat_sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._own = b""
        self._endpoint: asyncio.DatagramTransport | None = None

    async def open(self, loop: asyncio.AbstractEventLoop, own: bytes, on_datagram: Handler) -> None:
        sock = open_socket(self.cfg)
        try:
            self._beat_sock = open_socket(self.cfg, self.cfg.beat_port)
        except BusError:
            sock.close()
            raise
        self._sock, self._loop, self._own = sock, loop, own
        # The loop reads the socket (uvloop: in C, up to 32 datagrams a wake-up, until EAGAIN) and
        # hands each datagram over: no Python recvfrom per datagram, no BlockingIOError per wake-up.
        # The endpoint owns the socket from here: closing it closes the socket.
        try:
            self._endpoint, _ = await loop.create_datagram_endpoint(
                lambda: _Receiver(self, own, on_datagram), sock=sock
            )
        except BaseException:
            self._sock = None
            sock.close()
            self.close()
            raise

    def set_filter(
        self,
        src: str,
        inc: int,
        interest: Iterable[str],
        ignored: tuple[str, ...] = (),
        subjects: Mapping[str, Iterable[str]] | None = None,
    ) -> None:
        """Have the kernel drop what this module would drop unread (wire.kernel_filter), where it can."""
        if self._sock is not None:
            self._attach(self._sock, wire.kernel_filter(src, inc, interest, ignored, subjects))

    def ignore_beats_from(self, prefixes: tuple[str, ...]) -> None:
        if self._beat_sock is not None and prefixes:
            self._attach(self._beat_sock, wire.beat_filter(prefixes))

    def _attach(self, sock: socket.socket, code: list[tuple[int, int, int, int]]) -> None:
        if not self.kernel_filter:
            return
        program = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *c) for c in code))
        try:  # struct sock_fprog {unsigned short len; struct sock_filter *filter;}: the kernel copies the program
            sock.setsockopt(
                socket.SOL_SOCKET, SO_ATTACH_FILTER, struct.pack("HP", len(code), ctypes.addressof(program))
            )
        except OSError as e:  # not Linux, or filters forbidden: the bus drops the same datagrams itself
            self.log.warning("no kernel filter on the bus sockets (%s): every datagram wakes this module", e)
            self.kernel_filter = False

    def send(self, data: bytes) -> None:
        if self._sock is None:
            raise BusError("the bus transport is not open")
        self._sock.sendto(data, self._dest)

    def send_beat(self, data: bytes) -> None:
        if self._sock is None:
            raise BusError("the bus transport is not open")
        self._sock.sendto(data, self._beat_dest)

    def follow_beats(self, on_beats: Callable[[], None] | None) -> None:
        if self._beat_sock is None or self._loop is None:
            return
        if on_beats is None:
            self._loop.remove_reader(self._beat_sock.fileno())
        else:
            self._loop.add_reader(self._beat_sock.fileno(), on_beats)

    def beats(self) -> Iterator[bytes]:
        sock, own = self._beat_sock, self._own
        while sock is not None:
            try:
                data, self.source = sock.recvfrom(wire.MAX_DATAGRAM + 1)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self.log.warning("bus beat socket error: %s", e)
                return
            if not data.startswith(own):
                yield data

    def close(self) -> None:
        if self._endpoint is not None:
            self._endpoint.close()  # and the socket, on the loop's next turn
            self._endpoint = self._sock = None
        if self._beat_sock is not None:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(self._beat_sock.fileno())
            self._beat_sock.close()
            self._beat_sock = None


class _Receiver(asyncio.DatagramProtocol):
    """The bus socket's datagrams, as the loop reads them: our own skipped, the rest to the bus."""

    def __init__(self, transport: UdpTransport, own: bytes, on_datagram: Handler) -> None:
        self.transport, self.own, self.on_datagram = transport, own, on_datagram

    def datagram_received(self, data: bytes, addr: Any) -> None:
        if data.startswith(self.own):
            return  # our own datagram, looped back by the group
        self.transport.source = addr
        self.on_datagram(data)

    def error_received(self, exc: Exception) -> None:
        self.transport.log.warning("bus socket error: %s", exc)


class FaultInjector:
    """The configured faults (etc/cell.toml [bus.faults]) applied to every datagram a module receives,
    before the conversation layer sees it: drops, duplicates, and a datagram held back past the next."""

    def __init__(self, faults: Faults, name: str, stats: dict[str, int]) -> None:
        self.faults = faults
        self.rng = random.Random(None if faults.seed is None else f"{faults.seed}:{name}")
        self.stats = stats
        self._held: bytes | None = None

    def wrap(self, loop: asyncio.AbstractEventLoop, handle: Handler) -> Handler:
        """`handle` itself when no fault is configured (the hot path pays nothing), else through the faults."""
        if not self.faults.active:
            return handle

        def received(data: bytes) -> None:
            r = self.rng.random()
            f = self.faults
            if r < f.drop:
                self.stats["injected_drop"] += 1
                return
            if r < f.drop + f.duplicate:
                self.stats["injected_duplicate"] += 1
                handle(data)
            elif r < f.drop + f.duplicate + f.reorder and self._held is None:
                self.stats["injected_reorder"] += 1
                self._held = data  # delivered after the next datagram, or after 10 ms
                loop.call_later(0.01, release)
                return
            handle(data)
            release()

        def release() -> None:
            held, self._held = self._held, None
            if held is not None:
                handle(held)

        return received
