"""Datagram authentication: the seal every datagram carries, checked before anything else reads it.

A sealed datagram is the wire body (gwc/ipc/wire.py) followed by a trailer and two MACs:

    body | cell id (8) | flags (1) | module key id (2) | lot key id (2) | time (8, us since the epoch)
         | counter (8) | lot MAC (16) | module MAC (16)

Each MAC is keyed BLAKE2b-128 over everything before it: the lot MAC under the lot key, the module
MAC under the module key. Modules sign with both, lot scripts (flag LOT) with the lot key alone
(their module MAC is zeros). A module checks the module MAC, or the lot MAC of a lot-signed datagram;
a lot script, which holds no module key, checks the lot MAC. So a lot script can read the cell but
never speak as a module. A receiver drops, counting and never logging one line per datagram: another
cell's traffic (cell id), anything whose MAC does not check under a key it accepts, and replays: a datagram sealed
outside the replay window, or whose counter its sender (incarnation and name, per channel and key
role) already used. Only then is the body decoded. docs/protocol.md, *Authentication*, is normative.
"""

from __future__ import annotations

import collections
import hashlib
import hmac
import logging
import os
import struct
import time
from collections.abc import Iterator
from typing import Any

from gwc.config import BusConfig
from gwc.errors import BusError
from gwc.ipc import keys, wire
from gwc.ipc.transport import Transport
from gwc.log import FaultLog

TRAILER = struct.Struct("!8sBHHQQ")
MAC_BYTES = 16
SEAL_BYTES = TRAILER.size + 2 * MAC_BYTES
NO_MAC = bytes(MAC_BYTES)
LOT, BEAT = 1, 2  # flags: signed with the lot key; sent on the beat channel
WINDOW = 1024  # counters a sender may run ahead of one still accepted (reordering allowed)
_MASK = (1 << WINDOW) - 1
MIN_BODY = len(wire.HEADER) + 12  # magic, version, incarnation, src tag: what the replay window is keyed by
REPORT_EVERY = 10.0  # s between one source's drop summaries
MAX_SOURCES = 64  # sources counted apart in one summary; the rest together
_SRC_LEN_AT = wire.SRC_LEN_OFFSET


def mac_of(secret: bytes) -> hashlib.blake2b:
    """A keyed BLAKE2b-128 ready to be copied per datagram (copying skips the key schedule)."""
    return hashlib.blake2b(key=secret, digest_size=MAC_BYTES)


class DropLog:
    """Dropped traffic, counted per source and reported in one line per source at most every
    REPORT_EVERY: a quiet source's first drop at the next heartbeat, then a summary per interval."""

    def __init__(self, log: logging.Logger, stats: collections.Counter[str]) -> None:
        self.log = log
        self.stats = stats
        self._counts: dict[Any, collections.Counter[str]] = {}
        self._next: dict[Any, float] = {}  # source -> when its next line may be written

    def drop(self, reason: str, source: Any) -> None:
        self.stats["dropped_" + reason] += 1
        counts = self._counts.get(source)
        if counts is None:
            if len(self._counts) >= MAX_SOURCES:
                source = "other sources"
            counts = self._counts.setdefault(source, collections.Counter())
        counts[reason] += 1

    def report(self, now: float) -> None:
        """Write the lines that are due (called every heartbeat)."""
        for source, counts in list(self._counts.items()):
            if now < self._next.get(source, 0.0):
                continue
            what = ", ".join(f"{n} {reason.replace('_', ' ')}" for reason, n in counts.most_common())
            where = f"{source[0]}:{source[1]}" if isinstance(source, tuple) else source
            self.log.warning("dropped from %s (at most one line per %.0fs): %s", where, REPORT_EVERY, what)
            del self._counts[source]
            self._next[source] = now + REPORT_EVERY
        for source, at in list(self._next.items()):
            if at <= now and source not in self._counts:
                del self._next[source]


class Guard:
    """One bus member's seal: signs what it sends, checks what it receives (see the module docstring)."""

    def __init__(self, cfg: BusConfig, name: str, log: logging.Logger, stats: collections.Counter[str]) -> None:
        self.cfg = cfg
        self.role = keys.role_of(name)
        self._module = self.role == "module"  # checks module MACs (a lot script checks lot MACs)
        self.log = log
        self.stats = stats
        self.drops = DropLog(log, stats)
        self.faults = FaultLog(log, stats)
        self._path, keyset = keys.load(cfg, self.role)
        self._mtime = self._stat()
        self._use(keyset)
        self._counters = [0, 0]  # per channel: bus, beat
        # Per flags (channel, key role): inc + src tag -> [highest counter, bits, last seen]
        self._windows: tuple[dict[bytes, list[Any]], ...] = ({}, {}, {}, {})
        self._started = time.time()
        self._complaint = ""  # the key file's trouble last logged
        self.beat_drops = 0  # beats refused since the last heartbeat (the flood detector reads it)

    def _stat(self) -> int:
        try:
            return os.stat(self._path).st_mtime_ns
        except OSError:
            return 0

    def _use(self, keyset: keys.KeySet, now: float | None = None) -> None:
        now = time.time() if now is None else now
        self.keyset = keyset
        self._next_change = keyset.next_change(now)  # refresh() has nothing to do before then
        self.cell_id = keyset.cell_id
        # The keys accepted now, by id: (module keys, lot keys); open() picks one by the datagram's flag.
        accepted = [k for k in keyset.keys if k.accepted(now)]
        self._macs = tuple({k.id: mac_of(k.secret) for k in accepted if k.role == r} for r in ("module", "lot"))
        lot = self.role == "lot"
        lot_key = keyset.sending("lot", now)
        module_key = None if lot else keyset.sending("module", now)
        if lot_key is None or (module_key is None and not lot):
            raise BusError(f"{self._path} holds no {self.role} key to send with: `gwc key new --force`")
        self._send_flags = LOT if lot else 0
        self._lot_send = (lot_key.id, mac_of(lot_key.secret))
        self._module_send = (module_key.id, mac_of(module_key.secret)) if module_key else (0, None)

    @property
    def sealed(self) -> int:
        """Datagrams sealed on the bus channel so far (beats not counted)."""
        return self._counters[0]

    @property
    def key_ids(self) -> tuple[int, int]:
        """The ids of the (module, lot) keys this member signs with now (module 0: a lot script)."""
        return self._module_send[0], self._lot_send[0]

    def refresh(self) -> None:
        """At each heartbeat: re-read the key file if it changed, take up keys whose time has come."""
        mtime = self._stat()
        now = time.time()
        try:
            if mtime != self._mtime:
                self._mtime = mtime
                _, keyset = keys.load(self.cfg, self.role)
                self.log.info("key file %s changed: keys reloaded", self._path)
                self._use(keyset, now)
            elif now >= self._next_change:  # a rotated key's time came: senders take it up, or it is refused
                self._use(self.keyset, now)
        except BusError as e:  # keep the keys we have: a half-copied file must not stop the cell
            if str(e) != self._complaint:  # said once, not every heartbeat
                self._complaint = str(e)
                self.log.error("%s", e)
        else:
            self._complaint = ""
        horizon = now - 2 * self.cfg.replay_window
        for windows in self._windows:
            for k, w in list(windows.items()):
                if w[2] < horizon:
                    del windows[k]
        self.drops.report(time.monotonic())

    # ----------------------------------------------------------------- sending

    def seal(self, body: bytes, beat: bool = False) -> bytes:
        counters = self._counters
        counters[beat] += 1
        flags = self._send_flags | (BEAT if beat else 0)
        (lot_id, lot_mac), (module_id, module_mac) = self._lot_send, self._module_send
        head = body + TRAILER.pack(self.cell_id, flags, module_id, lot_id, int(time.time() * 1e6), counters[beat])
        h = lot_mac.copy()
        h.update(head)
        head += h.digest()
        if module_mac is None:
            return head + NO_MAC
        h = module_mac.copy()
        h.update(head)
        return head + h.digest()

    # ----------------------------------------------------------------- receiving

    def open(self, data: bytes, beat: bool, source: Any) -> tuple[bytes, bool] | None:
        """The body of an authentic, fresh datagram and whether the lot key signed it; None if dropped."""
        n = len(data)
        t = n - SEAL_BYTES
        if t < MIN_BODY:
            return self._drop("short", beat, source)
        cell, flags, module_id, lot_id, stamp, counter = TRAILER.unpack_from(data, t)
        if cell != self.cell_id:
            return self._drop("other_cell", beat, source)
        lot = bool(flags & LOT)
        # A module checks the module MAC (the lot MAC of a lot script's datagram); a lot script the lot MAC.
        if lot or not self._module:
            end = n - MAC_BYTES
            mac = self._macs[1].get(lot_id)
        else:
            end = n
            mac = self._macs[0].get(module_id)
        if mac is None:
            return self._drop("unknown_key", beat, source)
        h = mac.copy()
        h.update(data[: end - MAC_BYTES])
        if not hmac.compare_digest(h.digest(), data[end - MAC_BYTES : end]):
            return self._drop("bad_mac", beat, source)
        # Authentic from here: what follows holds only against replay and misuse of a key.
        if bool(flags & BEAT) != beat or flags & ~(LOT | BEAT):
            return self._drop("wrong_channel", beat, source)
        now = time.time()
        sealed = stamp / 1e6
        window = self.cfg.replay_window
        if not now - window <= sealed <= now + window:
            return self._drop("stale", beat, source)
        body = data[:t]
        if lot and not self._lot_name(body):  # before the window: a misused key moves no counter
            return self._drop("lot_key_misused", beat, source)
        key = data[4:MIN_BODY]
        windows = self._windows[flags]
        w = windows.get(key)
        if w is None:
            # A sender not heard from in this module's life. What it sealed before this module started
            # cannot have been sent to it: only a replay brings that (docs/protocol.md, Replay).
            if sealed < self._started - self.cfg.max_skew:
                return self._drop("replay", beat, source)
            windows[key] = [counter, 1, now]
        else:
            high = w[0]
            if counter > high:
                # A jump past the window forgets the window: constant time and memory for any
                # counter (a shift by the jump itself, 2^62 under a lot key, would need 2^59 bytes).
                ahead = counter - high
                w[0], w[1] = counter, ((w[1] << ahead) | 1) & _MASK if ahead < WINDOW else 1
            else:
                back = high - counter
                if back >= WINDOW or (w[1] >> back) & 1:
                    return self._drop("replay", beat, source)
                w[1] |= 1 << back
            w[2] = now
        return body, lot

    @staticmethod
    def _lot_name(body: bytes) -> bool:
        """Whether the sender names itself a lot entity (the lot key signs for nobody else)."""
        start = wire.BODY_OFFSET
        n = body[_SRC_LEN_AT] if len(body) > _SRC_LEN_AT else 0
        return body[start : start + min(n, 4)] == b"lot:"

    def _drop(self, reason: str, beat: bool, source: Any) -> tuple[bytes, bool] | None:
        """What open() returns for a dropped datagram (None), once it is counted."""
        self.drops.drop(reason, source)
        if beat:
            self.beat_drops += 1
        return None

    def beats(self, transport: Transport) -> Iterator[bytes]:
        """The bodies of the authentic, fresh beats that came since the last call."""
        for data in transport.beats():
            try:
                got = self.open(data, True, transport.source)
            except Exception as e:  # one beat no check foresaw must not leave the others unread
                self.faults.failed("opening a beat", e)
                continue
            if got is not None:
                yield got[0]
