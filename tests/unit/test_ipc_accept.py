"""Bus.accept: conversations handed to a handler as their opener is delivered, answered at once with
Conversation.reply, over both transports (the fixtures of test_ipc_bus_rules.py)."""

from __future__ import annotations

from gwc.config import BusConfig
from gwc.ipc.catalogue import message
from gwc.ipc.conversation import Conversation
from tests.unit.test_ipc_bus_rules import Make, keys_dir, known, run, transport, until

__all__ = ["keys_dir", "transport"]  # the autouse fixtures: both transports, a key folder per test


def _pong_at_once(conv: Conversation) -> None:
    assert conv.first is not None
    conv.reply(message("Pong", n=conv.first.first.n))
    conv.end()


def test_a_handler_given_to_accept_answers_each_conversation_at_once_and_in_order() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        asker, server = await make("asker", ()), await make("server")
        await known(asker, server)
        seen: list[int] = []

        def handler(conv: Conversation) -> None:
            assert conv.first is not None
            seen.append(conv.first.first.n)
            _pong_at_once(conv)

        server.accept(handler)
        for i in range(1, 51):
            conv, batch = await asker.request("PING", message("Ping", n=i), to="server", timeout=5)
            conv.end()
            assert batch.first.n == i
        assert seen == list(range(1, 51))
        assert await server.first_message(0.05) is None  # nothing queued behind the handler's back
        # Every Pong is acknowledged (the asker's acks ride on its next Ping, or go on their own).
        await until(lambda: not server.outbox.pending, "the server's Pongs to be acknowledged")
        assert not asker.outbox.pending

    run(t)


def test_conversations_queued_before_accept_go_to_the_handler_and_none_returns_to_the_queue() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        asker, server = await make("asker", ()), await make("server")
        await known(asker, server)
        first = await asker.start("PING", message("Ping", n=1), to="server")
        await until(lambda: server.stats["delivered"] >= 1, "the first Ping to be queued")
        server.accept(_pong_at_once)  # the queued one is answered now
        assert (await first.next_message(5)).first.n == 1
        server.accept(None)
        second = await asker.start("PING", message("Ping", n=2), to="server")
        conv = await server.first_message(5)
        assert conv is not None and conv.first is not None and conv.first.first.n == 2
        await conv.send(message("Pong", n=2))
        assert (await second.next_message(5)).first.n == 2

    run(t)


def test_a_failing_handler_costs_its_answer_only_and_the_bus_goes_on() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        asker, server = await make("asker", ()), await make("server")
        await known(asker, server)

        def handler(conv: Conversation) -> None:
            assert conv.first is not None
            if conv.first.first.n == 13:
                raise RuntimeError("a handler's bug")
            _pong_at_once(conv)

        server.accept(handler)
        unlucky = await asker.start("PING", message("Ping", n=13), to="server")
        conv, batch = await asker.request("PING", message("Ping", n=14), to="server", timeout=5)
        assert batch.first.n == 14
        conv.end()
        unlucky.end()
        assert server.stats["failed_handling a datagram"] == 1  # counted, logged once
        await until(lambda: not asker.outbox.pending, "the asker's Pings to be acknowledged, the failed one too")

    run(t)
