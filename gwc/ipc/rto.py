"""Retransmission timeouts that follow each peer's measured ack delay (RFC 6298's estimator).

The bus retransmitted a msg `ack_timeout` (20 ms) after sending it, whoever it went to. A peer busy
for longer than that (MSCHED in a step, a lot script sharing two cores with PostgreSQL) acknowledges
later, and every msg sent to it in the meantime went out twice: at 10,000 queued, seven in ten
datagrams MSCHED read in `gwc bench sched` were retransmissions, each a decode, an authentication
and a duplicate check for nothing, on the cores the scheduler needs.

Here each peer's ack delay is measured (from a msg's first send to the first ack of it from that
peer) and smoothed as TCP smooths its round-trip time: srtt += (d - srtt) / 8, rttvar += (|d - srtt|
- rttvar) / 4, timeout = srtt + 4 rttvar, between `floor` (the configured ack_timeout: a quiet cell
retransmits exactly as before) and `ceiling`. A broadcast waits as long as its slowest peer needs.

Samples are taken from the first send even of a msg that was retransmitted (no Karn's rule): on a
cell's LAN or loopback a datagram is rarely lost and often late, and Karn's rule would discard
exactly the samples of a late peer, so that its timeout never grew. A lost datagram's sample is too
long by the timeout it waited; the ceiling bounds it, and the smoothing forgets it.
"""

from __future__ import annotations

from collections.abc import Collection


class _Delay:
    __slots__ = ("rto", "rttvar", "srtt")

    def __init__(self, sample: float) -> None:
        self.srtt = sample
        self.rttvar = sample / 2
        self.rto = 0.0


class AckDelays:
    """Per peer: the smoothed ack delay, and the retransmission timeout it gives."""

    def __init__(self, floor: float, ceiling: float) -> None:
        self.floor = floor
        self.ceiling = max(floor, ceiling)
        self._peers: dict[str, _Delay] = {}
        self._above = 0  # peers whose timeout is above the floor (none: every lookup is the floor)

    def sample(self, peer: str, delay: float) -> None:
        """`peer` acknowledged a msg `delay` seconds after its first send."""
        d = min(max(delay, 0.0), self.ceiling)
        e = self._peers.get(peer)
        if e is None:
            e = self._peers[peer] = _Delay(d)
        else:
            e.rttvar += (abs(d - e.srtt) - e.rttvar) / 4
            e.srtt += (d - e.srtt) / 8
        was_above = e.rto > self.floor
        e.rto = min(max(e.srtt + 4 * e.rttvar, self.floor), self.ceiling)
        self._above += (e.rto > self.floor) - was_above

    def timeout(self, waiting: Collection[str]) -> float:
        """How long to wait for the acks of `waiting` before the first retransmission."""
        if not self._above:
            return self.floor
        peers = self._peers
        rto = self.floor
        for name in waiting:
            e = peers.get(name)
            if e is not None and e.rto > rto:
                rto = e.rto
        return rto

    def delays(self) -> dict[str, tuple[float, float]]:
        """peer -> (smoothed ack delay, timeout), in seconds (for diagnostics and tests)."""
        return {name: (e.srtt, e.rto) for name, e in self._peers.items()}
