"""Who is on the bus: each module's name, incarnation and interest, learnt from hellos (on the bus
port at sign-on and on a change, on the beat port every heartbeat) and lost by bye or silence.

And which wire version to speak (docs/protocol.md, "Versions"): every hello says the highest version
its sender speaks; a bus speaks the lowest of its live peers' (and of what untracked senders sent
lately), never above its own, so a cell upgraded host by host goes on talking and moves up once
every peer has moved."""

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
MAX_OLDER = 4096  # untracked senders whose older wire version is remembered past peer_timeout
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

    def speak(self, version: int) -> None:
        """Encode everything from now on in this wire version."""
        ...

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
        # Wire versions: the highest each tracked peer speaks (its hellos), the versions untracked senders
        # (ignored_peers, or not yet heard by hello) sent lately (name -> (version, when)), and ours.
        self.speaks: dict[str, int] = {}
        self.untracked: dict[str, tuple[int, float]] = {}
        # The last older version each untracked sender used, kept past peer_timeout (newest last, at most
        # MAX_OLDER): a broadcast that names it among its heard_by (a WC's Run_Complete to the lot whose
        # run it was, which may have been quiet for the whole run) goes out in a version it reads.
        self.older: collections.OrderedDict[str, int] = collections.OrderedDict()
        self.speaking = wire.VERSION
        self.highest = wire.VERSION  # what our hellos say we speak (this build's version)

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
                fields={wire.SPEAKS: self.highest},
                # A query (sign-on) goes out before any peer is known: in the oldest version we speak,
                # which every peer whose build reads it hears; it then answers with its own hello.
                version=wire.MIN_VERSION if query else self.speaking,
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
                Envelope(
                    kind="hello",
                    src=bus.name,
                    inc=bus.inc,
                    interest=interest,
                    subjects=self.subject_entries(),
                    fields={wire.SPEAKS: self.highest},
                    version=self.speaking,
                )
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
        if self.untracked:
            timeout = self.bus.cfg.peer_timeout
            old = [n for n, (_, at) in self.untracked.items() if now - at > timeout]
            for name in old:
                del self.untracked[name]
            if old:
                self.renegotiate()

    # ----------------------------------------------------------------- wire versions

    def heard_version(self, env: Envelope, now: float) -> None:
        """A datagram in another version than ours from a sender we hold no hello of (the bus calls this
        only then): one we ignore (a WC hears no lot's hellos, yet answers lots) must be answered in a
        version it reads, so an older one's msgs and acks lower what we speak for as long as it keeps
        sending. Not its hellos: a sign-on query is in the oldest version its sender speaks, whatever
        it speaks after (on_hello reads what it says)."""
        src, version = env.src, env.version
        if env.kind == "hello" or env.kind == "bye":
            return
        if version < wire.VERSION:
            self.older[src] = version
            self.older.move_to_end(src)
            if len(self.older) > MAX_OLDER:
                self.older.popitem(last=False)
        elif self.older:
            self.older.pop(src, None)  # restarted on a newer build
        if version < self.speaking or src in self.untracked:
            self.untracked[src] = (version, now)
            if version != self.speaking:
                self.renegotiate()

    def version_for(self, heard_by: Iterable[str]) -> int:
        """The version to encode a broadcast in that these untracked listeners must read: the lowest of
        what we speak and the last older version each of them sent (however long ago)."""
        older = self.older
        return min((self.speaking, *(older[n] for n in heard_by if n in older)))

    def renegotiate(self) -> None:
        """Speak the lowest version of our peers' (never above ours, never below the oldest we encode)."""
        lowest = min((self.highest, *self.speaks.values(), *(v for v, _ in self.untracked.values())))
        version = max(lowest, wire.MIN_VERSION)
        if version == self.speaking:
            return
        bus = self.bus
        older = sorted(n for n, v in self.speaks.items() if v == version)
        older += sorted(n for n, (v, _) in self.untracked.items() if v == version and n not in older)
        bus.log.info(
            "speaking wire version %d (this build speaks %d..%d%s)",
            version,
            wire.MIN_VERSION,
            wire.VERSION,
            f"; {', '.join(older[:5])}{' ...' if len(older) > 5 else ''} speak {version}" if older else "",
        )
        self.speaking = version
        self.beat_body = None
        bus.speak(version)

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
            if env.inc == bus.inc and env.src == bus.name:
                continue  # our own, in a version the transport's prefix test did not know (speaking an older one)
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
        speaks = env.fields.get(wire.SPEAKS) if env.fields else None
        speaks = speaks if type(speaks) is int and env.version <= speaks <= 255 else env.version
        if self.speaks.get(env.src) != speaks:
            self.speaks[env.src] = speaks
            self.untracked.pop(env.src, None)
            self.renegotiate()
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
        if self.speaks.pop(name, 256) <= self.speaking:  # it may have been the oldest
            self.renegotiate()
        if clean:
            self.gone[(name, peer.inc)] = None
            if len(self.gone) > MAX_GONE:
                self.gone.popitem(last=False)
        self.bus.outbox.forget_waiting(name, directed_too=clean)
        for cb in self.bus.peer_listeners:
            cb(name, None)
