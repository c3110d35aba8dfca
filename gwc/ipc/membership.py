"""Who is on the bus: each module's name, incarnation and interest, learnt from hellos (on the bus
port at sign-on and on a change, on the beat port every heartbeat) and lost by bye or silence."""

from __future__ import annotations

import collections
import functools
import logging
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Protocol

from gwc.config import BusConfig
from gwc.ipc import wire
from gwc.ipc.auth import Guard
from gwc.ipc.conversation import Names, Peer
from gwc.ipc.outbox import Outbox
from gwc.ipc.transport import Transport
from gwc.ipc.wire import Envelope
from gwc.log import TRACE, FaultLog

MAX_GONE = 1024  # incarnations that said bye, remembered so that their late beats are ignored
FLOOD_BEATS = 50  # beats refused in one heartbeat that make a flood
LOT = "lot:"  # lot scripts' bus names


def tick(heartbeat: float) -> float:
    """Seconds until the next heartbeat: the next multiple of `heartbeat` on the host's monotonic clock at
    least half a beat away. Every module of a host beats at the same ticks, so that a resting host wakes
    once a heartbeat for all of them, not once per module at scattered times: a cold wake-up costs the
    more, the fewer of its neighbours ran just before it (its code and the interpreter's are shared).
    Half a beat away, so that a timer that fires a little early does not beat twice."""
    return heartbeat - (time.monotonic() + heartbeat / 2) % heartbeat + heartbeat / 2


class MembershipHost(Protocol):
    """What the membership needs from its bus (gwc.ipc.bus.Bus is one)."""

    name: str
    inc: int
    cfg: BusConfig
    log: logging.Logger
    stats: collections.Counter[str]
    faults: FaultLog
    guard: Guard  # seals our hellos, checks the beats read
    transport: Transport
    outbox: Outbox  # sends hellos; stops waiting for acks of a peer gone
    ignored_peers: Names
    peer_listeners: list[Callable[[str, Peer | None], None]]

    @property
    def interests(self) -> frozenset[str]: ...

    @property
    def subjects(self) -> Mapping[str, frozenset[str]]: ...

    @property
    def signed_on(self) -> bool: ...

    def decode(self, data: bytes, what: str) -> Envelope | None:
        """The datagram's envelope; None (counted, logged) if it is malformed."""
        ...


def _level(bus: MembershipHost, name: str) -> int:
    """How a peer's coming and going is logged: a note, but trace where a lot script is either end. Lot
    scripts come and go with every lot: two lines per lot in every module's log, and a lot's own log
    began with one per module on the bus (a fifth of a forked lot script's log lines and their CPU)."""
    return TRACE if name.startswith(LOT) or bus.name.startswith(LOT) else logging.INFO


class Membership:
    """The peers one bus knows, kept for it (the bus reads `peers` on its hot paths)."""

    def __init__(self, bus: MembershipHost) -> None:
        self.bus = bus
        self.peers: dict[str, Peer] = {}
        self.beats: dict[bytes, tuple[str, int]] = {}  # each peer's last beat, as sent -> (name, inc)
        # Incarnations that said bye, newest last: a beat they sent before it, read after, is stale.
        self.gone: collections.OrderedDict[tuple[str, int], None] = collections.OrderedDict()
        self.beat_body: bytes | None = None  # our beat, encoded (send_beat); None after a change of interest
        self.following = False  # reading beats as they come (under a flood), not once a heartbeat

    def hello(self, query: bool = False, to: str | None = None) -> None:
        """Our hello on the bus port: at sign-on (a query), on a change of interest, to a querier."""
        bus = self.bus
        bus.outbox.send_envelope(
            Envelope(
                kind="hello",
                src=bus.name,
                inc=bus.inc,
                interest=tuple(sorted(bus.interests)),
                query=query,
                to=to,
                subjects=self.subject_entries(),
            )
        )

    def subject_entries(self) -> tuple[tuple[str, str], ...]:
        return tuple(sorted((c, s) for c, about in self.bus.subjects.items() for s in about))

    def take_beats(self, heartbeat: bool = False) -> None:
        """The beats that came, checked. A heartbeat that finds many refused (a flood on the beat port)
        switches to reading them as they come, so that the flood cannot fill the socket's buffer and
        push real beats out before they are read; a heartbeat without flood switches back."""
        bus = self.bus
        self.read_beats(bus.guard.beats(bus.transport))
        if not heartbeat:
            return  # called by the transport as beats come: the heartbeat decides
        flood = bus.guard.beat_drops > FLOOD_BEATS
        bus.guard.beat_drops = 0
        if flood != self.following:
            self.following = flood
            follow = functools.partial(bus.faults.run, "reading beats", self.take_beats)
            bus.transport.follow_beats(follow if flood else None)
            bus.log.warning("beat port %s", "flooded: beats read as they come" if flood else "quiet again")

    def send_beat(self) -> None:
        """Our hello, to the beat port: a change of interest or a query goes to the bus port instead."""
        bus = self.bus
        if not bus.signed_on:
            return
        beat = self.beat_body
        if beat is None:  # the same body every heartbeat until our interest changes: encoded once
            interest = tuple(sorted(bus.interests))
            beat = self.beat_body = wire.encode(
                Envelope(kind="hello", src=bus.name, inc=bus.inc, interest=interest, subjects=self.subject_entries())
            )
        try:
            bus.transport.send_beat(bus.guard.seal(beat, beat=True))
        except OSError as e:  # lost like a dropped datagram: the next beat makes up for it
            bus.stats["send_lost"] += 1
            bus.log.debug("beat not sent: %s", e)

    def expire(self, now: float) -> None:
        for name, peer in list(self.peers.items()):
            if now - peer.last_seen > self.bus.cfg.peer_timeout:
                self.left(name, "silent for %.1fs" % (now - peer.last_seen))

    def read_beats(self, datagrams: Iterable[bytes]) -> None:
        """Beats since the last heartbeat. They are late by up to a heartbeat, so one never brings in a
        new incarnation of a module we know (that comes by its sign-on hello on the bus port), nor back
        one that said bye: a dead incarnation's last beats, read after its successor's hello or its
        own bye, must not bring it back."""
        bus, peers, now = self.bus, self.peers, time.monotonic()
        for data in datagrams:
            known = self.beats.get(data)  # (not held in a local: a changed beat replaces the dict)
            if known is not None:  # the same beat as last time: nothing changed but the time
                peer = peers.get(known[0])
                if peer is not None and peer.inc == known[1]:
                    peer.last_seen = now  # all read in one go, at one time
                    bus.stats["beat"] += 1
                    continue
            env = bus.decode(data, "beat")
            if env is None:
                continue
            if env.kind != "hello":
                bus.stats["malformed"] += 1  # summarised with the drops: a line per datagram would flood the log
                bus.guard.drops.drop(f"{env.kind}_on_the_beat_port", env.src)
                continue
            if bus.ignored_peers and env.src.startswith(bus.ignored_peers):
                bus.stats["beat_ignored"] += 1  # (the kernel drops these where it can)
                continue
            bus.stats["beat"] += 1
            peer = self.peers.get(env.src)
            if (peer is None and (env.src, env.inc) not in self.gone) or (peer is not None and peer.inc == env.inc):
                self.on_hello(env, peer)
                self.beats = {d: k for d, k in self.beats.items() if k[0] != env.src}
                self.beats[data] = (env.src, env.inc)

    def on_hello(self, env: Envelope, peer: Peer | None) -> None:
        bus = self.bus
        if bus.ignored_peers and env.src.startswith(bus.ignored_peers):
            return  # not tracked, and it does not track us: no answer to its query either
        now = time.monotonic()
        interest = frozenset(env.interest)
        subjects: dict[str, frozenset[str]] = {}
        if env.subjects:
            about: dict[str, set[str]] = {}
            for cls, subject in env.subjects:
                about.setdefault(cls, set()).add(subject)
            subjects = {cls: frozenset(s) for cls, s in about.items()}
        if peer is None or peer.inc != env.inc:
            if peer is not None:
                # The old process is gone. Listeners get the new Peer (its inc differs from the one they
                # knew); msgs still waiting for the old one are acked by the new one and dropped as late.
                bus.log.log(_level(bus, env.src), "%s restarted (incarnation %x -> %x)", env.src, peer.inc, env.inc)
            else:
                bus.log.log(_level(bus, env.src), "%s joined the bus", env.src)
            peer = Peer(env.src, env.inc, interest, now, subjects)
            self.peers[env.src] = peer
            for cb in self.bus.peer_listeners:
                cb(env.src, peer)
        else:
            if interest != peer.interest or subjects != peer.subjects:
                peer.interest, peer.subjects = interest, subjects
                # It no longer listens to some classes (or subjects): it will not ack broadcasts of them.
                self.bus.outbox.forget_waiting(env.src, directed_too=False, unless=peer)
            peer.last_seen = now
        if env.query:
            self.hello(to=env.src)  # addressed to the newcomer: N answers to one module, not N x N receptions

    def left(self, name: str, why: str, clean: bool = False) -> None:
        peer = self.peers.pop(name, None)
        if peer is None:
            return
        self.bus.log.log(_level(self.bus, name), "%s left the bus (%s)", name, why)
        self.beats = {d: k for d, k in self.beats.items() if k[0] != name}
        if clean:
            self.gone[(name, peer.inc)] = None
            if len(self.gone) > MAX_GONE:
                self.gone.popitem(last=False)
        self.bus.outbox.forget_waiting(name, directed_too=clean)
        for cb in self.bus.peer_listeners:
            cb(name, None)
