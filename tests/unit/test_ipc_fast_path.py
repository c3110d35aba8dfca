"""The bus's fast paths (docs/performance.md, "The bus") and their fallbacks: a msg that is one message,
next in its stream with nothing waiting, is delivered without the reorder machinery; anything else
(out of order, a duplicate or retransmission, a batch, a stream first met past its base, an invalid
message) goes the general way and keeps every rule. The generated message checks accept and refuse
exactly what the full check does; the msg encoder writes exactly the general encoder's bytes."""

from __future__ import annotations

import asyncio
import logging
import random
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from gwc.config import BusConfig
from gwc.errors import MessageError
from gwc.ipc import catalogue, wire
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.conversation import Batch
from gwc.ipc.memory import MemoryTransport
from tests.unit import test_ipc_bus_rules as rules

Pair = tuple[Bus, Bus, list[bytes], list[int]]


def _run(tmp_path: Path, test: Callable[[Pair], Awaitable[None]]) -> None:
    """Buses a and b on a private in-memory bus; a's msgs are captured, not sent (fed to b by the test,
    in any order, any number of times); b's calls of the general path (Inbound.place) are counted."""
    rules.KEYS_DIR = tmp_path  # private_cfg makes the bus keys there
    cfg = rules.private_cfg(ack_timeout=5.0)  # no retransmission of a's own while the test feeds them

    async def main() -> None:
        a = Bus("a", cfg, logging.getLogger("gwc.test.a"), (), MemoryTransport(cfg))
        b = Bus("b", cfg, logging.getLogger("gwc.test.b"), ("PING",), MemoryTransport(cfg))
        await a.sign_on()
        await b.sign_on()
        try:
            await rules.known(a, b)
            sent: list[bytes] = []
            send = a._transmit
            a._transmit = lambda data: sent.append(data) if _is_msg(data) else send(data)  # type: ignore[method-assign]
            general: list[int] = []
            place = b._inbound.place
            b._inbound.place = lambda env, msg, now: (general.append(env.idx), place(env, msg, now))[1]  # type: ignore[method-assign]
            await asyncio.wait_for(test((a, b, sent, general)), 30)
        finally:
            await a.close(flush=0)
            await b.close(flush=0)

    asyncio.run(main())


def _is_msg(body: bytes) -> bool:
    return body[wire.OFF_KIND] == 0


def feed(a: Bus, b: Bus, body: bytes) -> None:
    """Hand b one of a's datagrams, sealed as a sends it (a retransmission is the same body sealed again)."""
    b._handle(a.guard.seal(body))


async def opened(b: Bus) -> Any:
    conv = await b.first_message(2)
    assert conv is not None
    return conv


def test_one_message_in_order_takes_the_fast_path_and_is_delivered_once(tmp_path: Path) -> None:
    async def t(p: Pair) -> None:
        a, b, sent, general = p
        conv = await a.start("PING", message("Ping", n=1), to="b")
        feed(a, b, sent[0])
        inc = await opened(b)
        assert inc.first.first.n == 1 and general == []
        feed(a, b, sent[0])  # a retransmission: acknowledged again, not delivered again
        feed(a, b, sent[0])
        assert b.stats["duplicates"] == 2 and b.stats["delivered"] == 1
        assert await b.first_message(0.1) is None
        await conv.send(message("Ping", n=2))  # the next in the same stream: fast too
        feed(a, b, sent[1])
        assert (await inc.next_message(2)).first.n == 2 and general == []

    _run(tmp_path, t)


def test_out_of_order_messages_fall_back_and_are_delivered_in_order(tmp_path: Path) -> None:
    async def t(p: Pair) -> None:
        a, b, sent, general = p
        conv = await a.start("PING", message("Ping", n=0), to="b")
        for n in (1, 2):
            await conv.send(message("Ping", n=n))
        feed(a, b, sent[0])
        inc = await opened(b)
        feed(a, b, sent[2])  # idx 2 before idx 1: held, through the general path
        assert general == [2] and not inc._inbox
        feed(a, b, sent[1])  # fills the gap: both delivered, in order
        assert general == [2, 1]
        assert [(await inc.next_message(2)).first.n for _ in range(2)] == [1, 2]
        feed(a, b, sent[1])  # and a late duplicate is still only acknowledged
        assert b.stats["duplicates"] == 1 and b.stats["delivered"] == 3

    _run(tmp_path, t)


def test_a_stream_first_met_past_its_base_waits_for_what_is_missing(tmp_path: Path) -> None:
    async def t(p: Pair) -> None:
        a, b, sent, general = p
        conv = await a.start("PING", message("Ping", n=0), to="b")
        await conv.send(message("Ping", n=1))  # idx 1, base 0: idx 0 is not settled
        feed(a, b, sent[1])
        assert general == [1] and await b.first_message(0.1) is None  # no opener yet: nothing delivered
        feed(a, b, sent[0])
        inc = await opened(b)
        assert inc.first.first.n == 0 and (await inc.next_message(2)).first.n == 1

    _run(tmp_path, t)


def test_a_batch_falls_back_and_is_delivered_whole(tmp_path: Path) -> None:
    async def t(p: Pair) -> None:
        a, b, sent, general = p
        await a.start("PING", message("Ping", n=0), message("Ping", n=1), message("Ping", n=2), to="b")
        assert len(sent) == 3
        feed(a, b, sent[0])
        feed(a, b, sent[1])
        assert await b.first_message(0.1) is None  # not before the batch is whole
        feed(a, b, sent[2])
        inc = await opened(b)
        assert isinstance(inc.first, Batch) and [m.n for m in inc.first.messages] == [0, 1, 2]
        assert general == [0, 1, 2]

    _run(tmp_path, t)


def test_an_invalid_message_falls_back_holds_its_place_and_is_dropped(tmp_path: Path, caplog: Any) -> None:
    async def t(p: Pair) -> None:
        a, b, sent, general = p
        conv = await a.start("PING", message("Ping", n=0), to="b")
        await conv.send(message("Ping", n=1))
        feed(a, b, sent[0])
        inc = await opened(b)
        env = wire.decode(sent[1])
        bad = wire.encode_msg(
            wire.origin("a", a.inc), env.seq, env.conv, env.cls, env.idx, 0, 0, env.base, "b", "Ping", {"n": "one"}
        )
        feed(a, b, bad)
        assert general == [1] and b.stats["invalid"] == 1 and not inc._inbox
        await conv.send(message("Ping", n=2))  # the stream goes on past it
        feed(a, b, sent[2])
        assert (await inc.next_message(2)).first.n == 2

    with caplog.at_level(logging.WARNING):
        _run(tmp_path, t)
    assert "dropped invalid Ping from a" in caplog.text


def test_the_generated_checks_agree_with_the_full_check() -> None:
    class Int(int):
        pass

    values: list[Any] = [None, 0, 7, True, 1.5, float("nan"), "", "x", "a\0b", "y" * 201, "z" * 999, [], {}, Int(3)]
    rnd = random.Random(38)
    tried = 0
    for mc in catalogue.MESSAGE_CLASSES.values():
        names = [f.name for f in mc.fields]
        for _ in range(200):
            d = {n: rnd.choice(values) for n in names if rnd.random() < 0.8}
            if rnd.random() < 0.05:
                d["bogus"] = 1

            def outcome(check: Callable[[dict[str, Any]], None], d: dict[str, Any] = d) -> str | None:
                try:
                    check(d)
                except MessageError as e:
                    return str(e)
                return None

            assert outcome(mc.check) == outcome(mc.full_check), (mc.name, d)
            tried += 1
    assert tried > 1000
    with pytest.raises(MessageError, match="n must be int"):
        message("Ping", n=True)
    assert message("Ping", n=Int(3)).n == 3  # what only the full check accepts, it still accepts


@pytest.mark.parametrize("version", [wire.MIN_VERSION, wire.VERSION])
def test_the_msg_encoder_writes_the_general_encoders_bytes(version: int) -> None:
    orig = wire.origin("bench.a", 12345, version, catalogue.fields_after(version) or None)
    for acks in ((), (1,), (3, 9, 2**40)):
        for to in (None, "bench.srv"):
            for subject in ("", "mill_1"):
                for fields in ({}, {"n": 1, "payload": "x"}, {"a": [1, {"b": None}], "é": "ü"}):
                    args = (5, "c.1.2", "PING", 3, 2, 0, 1, to, "Ping", fields, subject)
                    ti = 77 if acks else 0
                    assert wire.encode_msg(orig, *args, acks, ti) == wire.encode_parts(orig, "msg", *args, acks, ti), (
                        acks,
                        to,
                        subject,
                        fields,
                    )
    with pytest.raises(MessageError, match="over the bus limit"):
        wire.encode_msg(orig, 1, "c.1.2", "PING", 0, 0, 0, 0, None, "Ping", {"payload": "x" * 70_000})


def test_the_bytecode_count_of_a_round_trip_is_deterministic_and_names_the_hot_path() -> None:
    """`gwc bench bus --bytecodes`: the same count twice, and the fast path's steps in it, not the general ones."""
    from gwc.bench.bus import bytecodes

    first, second = bytecodes(60, warm=20), bytecodes(60, warm=20)
    assert abs(first["bytecodes"] - second["bytecodes"]) <= 0.02 * first["bytecodes"]
    per = first["per_function"]
    assert per["order.py:in_order"][1] == 2.0 and "order.py:place" not in per  # one msg each way, both fast
    assert per["wire.py:encode_msg"][1] == 2.0  # (encode_parts: hellos only)


def test_the_ack_timer_lets_an_answer_in_the_same_turn_take_the_ack_along() -> None:
    """The ack timer runs before the loop turn's ready callbacks: it flushes at the end of the turn, so
    that a task woken by the msg and answering it takes the ack along and no ack datagram goes."""
    import collections

    from gwc.ipc.outbox import Outbox

    async def main() -> None:
        sent: list[bytes] = []
        outbox = Outbox("a", 1, BusConfig(), logging.getLogger("gwc.test.a"), collections.Counter(), sent.append)
        outbox.loop = asyncio.get_running_loop()
        try:
            outbox.ack(("b", 2), 5)
            outbox._acks_due()  # the timer fires ...
            assert outbox.take_acks(("b", 2)) == [5]  # ... and an answer in the same turn takes the ack
            await asyncio.sleep(0)
            assert sent == []
            outbox.ack(("b", 2), 6)
            outbox._acks_due()  # nobody answers: an ack datagram at the end of the turn
            await asyncio.sleep(0)
            assert len(sent) == 1 and wire.decode(sent[0]).acks == (6,)
            outbox.ack(("b", 2), 7)
            outbox._acks_due()
            outbox.close()  # a flush put at the end of the turn is cancelled with the timers
            await asyncio.sleep(0)
            assert len(sent) == 1
        finally:
            outbox.close()

    asyncio.run(main())
