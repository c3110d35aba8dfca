"""Retransmission timeouts that follow each peer's ack delay (gwc/ipc/rto.py): the estimator alone,
and two buses in this process where one acknowledges later than the configured ack_timeout."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import replace
from pathlib import Path

import pytest

from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.memory import MemoryTransport
from gwc.ipc.rto import AckDelays
from tests.unit import test_ipc_bus_rules as rules


def test_a_quiet_peer_keeps_the_floor_and_a_late_one_gets_a_longer_timeout() -> None:
    d = AckDelays(floor=0.02, ceiling=0.5)
    assert d.timeout(["a", "b"]) == 0.02  # nobody measured: the configured ack_timeout
    for _ in range(20):
        d.sample("a", 0.005)  # acks within the receiver's gathering delay
        d.sample("b", 0.060)  # a peer busy for 60 ms at a time
    assert d.timeout(["a"]) == 0.02
    assert 0.060 <= d.timeout(["b"]) < 0.1
    assert d.timeout(["a", "b"]) == d.timeout(["b"])  # a broadcast waits for its slowest peer
    assert d.timeout(["c"]) == 0.02  # not measured yet
    for _ in range(60):
        d.sample("b", 0.005)  # b is quick again: its timeout comes back down to the floor
    assert d.timeout(["b"]) == 0.02
    d.sample("a", 10.0)  # a lost datagram's sample is bounded by the ceiling
    assert d.timeout(["a"]) == 0.5


def test_a_peer_that_acknowledges_late_is_no_longer_sent_duplicates(tmp_path: Path) -> None:
    """b gathers its acks for 50 ms, longer than a's 20 ms ack_timeout: a retransmitted each msg at
    first; after a few measured delays it waits long enough, and sends each msg once (or nearly)."""
    rules.KEYS_DIR = tmp_path
    cfg = rules.private_cfg(ack_timeout=0.02)

    async def main() -> None:
        a = Bus("a", cfg, logging.getLogger("gwc.test.a"), (), MemoryTransport(cfg))
        b = Bus("b", cfg, logging.getLogger("gwc.test.b"), ("PING",), MemoryTransport(cfg))
        await a.sign_on()
        await b.sign_on()
        try:
            b.outbox.cfg = replace(cfg, ack_timeout=0.2)  # b flushes its acks a quarter of that later
            await rules.known(a, b)

            async def one(n: int) -> None:
                conv = await a.start("PING", message("Ping", n=n), to="b")
                inc = await b.first_message(5)
                assert inc is not None and inc.first.first.n == n
                await rules.until(lambda: not a.outbox.pending, f"b's ack of Ping {n}")
                conv.end()
                inc.end()

            for n in range(10):  # warm-up: the first msgs go out twice or more
                await one(n)
            warm = a.stats["retransmitted"]
            assert warm > 0
            for n in range(10, 30):
                await one(n)
            # With the fixed timeout every one of these 20 goes out twice; a stall of the loaded test
            # machine longer than the peer's measured variance may still cost one or two.
            assert a.stats["retransmitted"] - warm <= 3, "msgs to a late peer were still retransmitted"
            srtt, rto = a.outbox.ack_delays.delays()["b"]
            assert srtt >= 0.04 and rto > srtt
        finally:
            await a.close(flush=0)
            await b.close(flush=0)

    asyncio.run(asyncio.wait_for(main(), 60))


@pytest.mark.parametrize("floor", [0.02, 0.2])
def test_the_timeout_never_goes_below_the_configured_ack_timeout(floor: float) -> None:
    d = AckDelays(floor=floor, ceiling=0.5)
    for _ in range(50):
        d.sample("a", 0.0001)
    assert d.timeout(["a"]) == floor
