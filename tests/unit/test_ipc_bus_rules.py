"""The bus's delivery rules at their edges, with several Bus objects in this process: resumed
conversations, restarts, late replies, interest changes, dedup, close. Every test runs twice, over a
real multicast group (udp) and over the in-memory transport (memory): the conversation layer must
behave the same over both. (The multi-process behaviour is in test_bus.py.)"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from gwc.config import BusConfig, Faults
from gwc.errors import BusError
from gwc.ipc import keys, wire
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.memory import MemoryTransport
from gwc.ipc.transport import Transport

Make = Callable[..., Awaitable[Bus]]
TRANSPORT = "udp"  # set for each test by the fixture below
KEYS_DIR = Path()  # the running test's own folder, for its bus keys (the fixture below)


@pytest.fixture(autouse=True, params=["udp", "memory"])
def transport(request: Any) -> Any:
    global TRANSPORT
    TRANSPORT = request.param
    yield request.param
    TRANSPORT = "udp"


@pytest.fixture(autouse=True)
def keys_dir(tmp_path: Path) -> None:
    global KEYS_DIR
    KEYS_DIR = tmp_path  # pytest removes it (a mkdtemp of our own was left behind by every test)


def transport_for(cfg: BusConfig) -> Transport | None:
    """The transport of the running test's kind (None: the bus's default, UDP multicast)."""
    return MemoryTransport(cfg) if TRANSPORT == "memory" else None


def private_cfg(**kw: Any) -> BusConfig:
    """A bus of its own (group, port, keys)."""
    rnd = random.Random()
    where = KEYS_DIR
    cfg = BusConfig(
        group=f"239.255.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}",
        port=rnd.randrange(20000, 60000),
        heartbeat=0.1,
        peer_timeout=1.0,
        key_file=str(where / "cell.key"),
        lot_key_file=str(where / "lot.key"),
        **kw,
    )
    keys.new(cfg)
    return cfg


async def until(predicate: Callable[[], Any], what: str, timeout: float = 10.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not predicate():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


def run(test: Callable[[Make, BusConfig], Awaitable[None]], **cfg: Any) -> None:
    """Run an async test with a factory of signed-on buses, all closed afterwards."""
    config = private_cfg(**cfg)

    async def main() -> None:
        buses: list[Bus] = []

        async def make(
            name: str,
            interest: tuple[str, ...] = ("PING",),
            c: BusConfig = config,
            ignored: tuple[str, ...] = (),
        ) -> Bus:
            bus = Bus(name, c, logging.getLogger(f"gwc.test.{name}"), interest, transport_for(c), ignored)
            await bus.sign_on()
            buses.append(bus)
            return bus

        try:
            await asyncio.wait_for(test(make, config), 60)
        finally:
            for b in buses:
                await b.close(flush=0.2)

    asyncio.run(main())


async def known(a: Bus, *others: Bus) -> None:
    await until(
        lambda: all(o.name in a.peers() for o in others) and all(a.name in o.peers() for o in others),
        "peers to see each other",
    )


def test_a_conversation_ended_and_resumed_in_the_same_incarnation_goes_on() -> None:
    """MSCHED's pattern: answer Machine_Req_Ack, end; later resume and send Machine_Req_Comp."""

    async def t(make: Make, cfg: BusConfig) -> None:
        lot, sched = await make("lot:1"), await make("msched", ("MACH_REQ",))
        await known(lot, sched)
        conv = await lot.start(
            "MACH_REQ",
            message("Machine_Request", entity_id=1, op_type="x", num_machines=1),
            message("Machine_Entry", machine_id="wc1"),
            to="msched",
        )
        inc = await sched.first_message(5)
        assert inc is not None and [m.name for m in inc.first.messages] == ["Machine_Request", "Machine_Entry"]
        await inc.send(message("Machine_Req_Ack", ack_code="ACK_OK", request_key=5))
        inc.end()
        assert (await conv.next_message(5)).first.request_key == 5
        again = sched.resume(conv.id, "MACH_REQ", "lot:1")
        await again.send(
            message("Machine_Req_Comp", ack_code="ACK_OK", entity_id=1, num_machines=1),
            message("Reserved_Machine", machine_id="wc1"),
        )
        comp = await conv.next_message(5)
        assert [m.name for m in comp.messages] == ["Machine_Req_Comp", "Reserved_Machine"]
        await conv.send(message("Request_Comp_Ack", entity_id=1, ack_code="ACK_OK"))
        assert (await again.next_message(5)).first.name == "Request_Comp_Ack"

    run(t)


def test_a_restarted_module_resumes_a_conversation_and_both_sides_go_on() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        lot, sched = await make("lot:2"), await make("msched", ("MACH_REQ",))
        await known(lot, sched)
        conv = await lot.start(
            "MACH_REQ",
            message("Machine_Request", entity_id=2, op_type="x", num_machines=1),
            message("Machine_Entry", machine_id="wc1"),
            to="msched",
        )
        inc = await sched.first_message(5)
        await inc.send(message("Machine_Req_Ack", ack_code="ACK_OK", request_key=9))
        await conv.next_message(5)
        await sched.close()  # MSCHED dies ...
        joined: list[tuple[str, bool]] = []
        lot.peer_listeners.append(lambda name, peer: joined.append((name, peer is not None)))
        sched2 = await make("msched", ("MACH_REQ",))  # ... and comes back as a new incarnation
        await known(lot, sched2)
        again = sched2.resume(conv.id, "MACH_REQ", "lot:2")
        await again.send(message("Machine_Req_Comp", ack_code="NO_MACHINE", entity_id=2, num_machines=0))
        assert (await conv.next_message(5)).first.ack_code == "NO_MACHINE"
        await conv.send(message("Request_Comp_Ack", entity_id=2, ack_code="ACK_OK"))
        # The lot's idx is 2 by now; the new incarnation has no state for it, and `base` tells it 0-1 are settled.
        assert (await again.next_message(5)).first.name == "Request_Comp_Ack"
        assert ("msched", True) in joined

    run(t)


def test_a_late_reply_to_an_ended_conversation_is_logged_and_dropped(caplog: Any) -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b")
        await known(a, b)
        conv = await a.start("PING", message("Ping", n=1), to="b")
        inc = await b.first_message(5)
        conv.end()  # the initiator gave up (say, it timed out)
        await inc.send(message("Pong", n=1))
        await until(lambda: a.stats["late"] == 1, "the late reply to be noticed")
        assert await a.first_message(0.2) is None, "a late reply never opens a new conversation"
        await until(lambda: not b._pending, "the late reply to be acknowledged all the same")

    with caplog.at_level(logging.WARNING):
        run(t)
    assert "late Pong from b in ended conversation" in caplog.text


def test_a_module_that_drops_an_interest_is_not_waited_for() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b", ("UPD_ME_ST",))
        await known(a, b)
        b.set_interest(())
        await until(lambda: "UPD_ME_ST" not in a.peers()["b"].interest, "a to hear b's new interest")
        conv = await a.start("UPD_ME_ST", message("Update_ME_Status", machine_id="x", status="Idle"))
        conv.end()
        assert not a._pending, "nobody listens: nothing to wait for"
        b.set_interest(("UPD_ME_ST",))
        await until(lambda: "UPD_ME_ST" in a.peers()["b"].interest, "a to hear b listens again")
        await a.start("UPD_ME_ST", message("Update_ME_Status", machine_id="y", status="Idle"))
        b.set_interest(())  # b loses interest before it could ack (its hello tells a)
        await until(lambda: not a._pending, "a to stop waiting for b")

    run(t)


def test_a_module_hears_a_class_about_its_subjects_only_and_is_waited_for_only_there() -> None:
    """A lot hears UPD_ME_ST and RUN_COMPL about its own machines (docs/protocol.md, "Subjects"): the
    others never reach its application (over UDP the kernel drops them unread), the sender waits for its
    ack only for what it hears, and a subject it drops is no longer waited for."""

    async def t(make: Make, cfg: BusConfig) -> None:
        ms, lot = await make("ms", ()), await make("lot:1", ("MOD_DIED",))
        whole = await make("msched", ("UPD_ME_ST",))
        lot.set_interest(("MOD_DIED",), subjects={"UPD_ME_ST": ("wc1", "wc3")})
        await known(ms, lot, whole)
        await until(lambda: ms.listeners_of("UPD_ME_ST", "wc1") == ["lot:1", "msched"], "ms to hear lot:1's subjects")
        assert ms.listeners_of("UPD_ME_ST", "wc2") == ["msched"] and ms.listeners_of("UPD_ME_ST") == ["msched"]
        read = lot.stats["msg"] - lot.stats["duplicates"]  # (a retransmission under load is read again)
        for m in ("wc1", "wc2", "wc3", "wc2"):
            sent = await ms.start("UPD_ME_ST", message("Update_ME_Status", machine_id=m, status="Idle"))
            assert set(ms._pending[max(ms._pending)].waiting) == ({"lot:1", "msched"} if m != "wc2" else {"msched"})
            sent.end()
        heard = []
        for _ in range(2):
            conv = await lot.first_message(5)
            assert conv is not None and conv.first is not None
            heard.append(conv.first.first.machine_id)
            conv.end()
        assert heard == ["wc1", "wc3"] and await lot.first_message(0.2) is None
        got = [(await whole.first_message(5)) for _ in range(4)]
        assert [c.first.first.machine_id for c in got if c and c.first] == ["wc1", "wc2", "wc3", "wc2"]
        await until(lambda: not ms._pending, "every ack")
        if TRANSPORT == "udp":  # the kernel kept wc2's news from the lot: it read two msgs, not four
            assert lot.stats["msg"] - lot.stats["duplicates"] - read == 2
        await ms.start("UPD_ME_ST", message("Update_ME_Status", machine_id="wc3", status="Setup"))
        lot.set_interest(("MOD_DIED",), subjects={"UPD_ME_ST": ("wc1",)})  # before it could ack: its hello tells
        await until(lambda: not ms._pending, "ms to stop waiting for lot:1 about wc3")
        assert ms.stats["gave_up"] == 0

    run(t)


def test_a_repeated_datagram_is_acknowledged_again_but_delivered_once() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b")
        await known(a, b)
        sent: list[bytes] = []
        orig = a._transmit
        a._transmit = lambda data: (sent.append(data), orig(data))[1]  # type: ignore[method-assign]
        conv = await a.start("PING", message("Ping", n=7), to="b")
        for _ in range(3):
            orig(sent[0])
        inc = await b.first_message(5)
        assert inc is not None and inc.first.first.n == 7
        assert await b.first_message(0.3) is None
        assert b.stats["duplicates"] == 3
        conv.end()

    run(t, ack_timeout=2.0)  # no retransmission of a's own meanwhile (a fourth duplicate under load)


def test_many_messages_received_then_one_sent_back_still_fits_a_datagram() -> None:
    """Acks due ride on the next msg only up to a limit; the rest go in ack datagrams."""

    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b")
        await known(a, b)
        convs = [await a.start("PING", message("Ping", n=i), to="b") for i in range(300)]
        incoming = [await b.first_message(5) for _ in range(300)]
        await incoming[0].send(message("Pong", n=0))
        assert (await convs[0].next_message(5)).first.n == 0
        await until(lambda: not a._pending, "all 300 to be acknowledged")

    run(t, ack_timeout=0.2)  # acks pile up before the flush


def test_a_restart_is_reported_with_the_new_incarnation_and_an_old_bye_is_ignored() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b")
        await known(a, b)
        events: list[tuple[str, int | None]] = []
        a.peer_listeners.append(lambda name, peer: events.append((name, peer.inc if peer else None)))
        old_inc = b.inc
        b._heartbeat.cancel()  # the old one dies without a word (its last beats may still be on their way) ...
        b._transport.close()
        b._open = False
        b2 = Bus("b", cfg, logging.getLogger("gwc.test.b2"), ("PING",), transport_for(cfg))
        await b2.sign_on()
        try:
            await until(lambda: a.peers()["b"].inc == b2.inc, "a to see the new incarnation")
            assert events[:1] == [("b", b2.inc)]
            await asyncio.sleep(3 * cfg.heartbeat)  # beats read meanwhile, the dead one's too: b2 stays
            assert a.peers()["b"].inc == b2.inc and events == [("b", b2.inc)]
            old_bye = wire.encode(wire.Envelope(kind="bye", src="b", inc=old_inc))
            a._handle(a._guard.seal(old_bye))  # ... and a stray bye of the old incarnation changes nothing
            assert "b" in a.peers()
        finally:
            await b2.close()
        await until(lambda: "b" not in a.peers(), "the clean bye of the new incarnation")

    run(t)


def test_closing_the_bus_fails_every_waiter_at_once() -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        a = await make("a", ())
        conv = await a.start("PING", message("Ping", n=1))
        waiter = asyncio.ensure_future(conv.next_message(30))
        getter = asyncio.ensure_future(a.first_message())
        await asyncio.sleep(0.05)
        await a.close(flush=0)
        with pytest.raises(BusError, match="closed"):
            await asyncio.wait_for(waiter, 2)
        assert await asyncio.wait_for(getter, 2) is None

    run(t)


def test_liveness_survives_lost_hellos_when_other_traffic_flows() -> None:
    """Under the fault injector a peer's hellos can all be lost; any datagram from it proves life."""

    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b")
        await known(a, b)
        left: list[str] = []
        a.peer_listeners.append(lambda name, peer: peer is None and left.append(name))
        b._members.hello = lambda query=False, to=None: None  # type: ignore[method-assign]  # b's hellos never arrive
        loop = asyncio.get_running_loop()
        end = loop.time() + 2 * cfg.peer_timeout
        n = 0
        while loop.time() < end:
            inc_task = asyncio.ensure_future(b.first_message(5))
            conv, _ = await asyncio.gather(a.start("PING", message("Ping", n=n), to="b"), inc_task)
            await inc_task.result().send(message("Pong", n=n))
            await conv.next_message(5)
            conv.end()
            n += 1
            await asyncio.sleep(0.05)
        assert left == []

    run(t)


def test_invalid_message_in_a_batch_drops_the_batch_not_the_stream(caplog: Any) -> None:
    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("a", ()), await make("b")
        await known(a, b)
        conv = await a.start("PING", message("Ping", n=1), to="b")
        inc = await b.first_message(5)
        assert inc is not None
        # A follower that does not fit its class (as from a buggy or older sender), then a good batch.
        bad = wire.Envelope(
            kind="msg",
            src="a",
            inc=a.inc,
            seq=a._seq + 1,
            conv=conv.id,
            cls="PING",
            idx=1,
            more=1,
            to="b",
            msg="Ping",
            fields={"n": 2},
        )
        bad2 = wire.Envelope(
            kind="msg",
            src="a",
            inc=a.inc,
            seq=a._seq + 2,
            conv=conv.id,
            cls="PING",
            idx=2,
            part=1,
            to="b",
            msg="Ping",
            fields={"n": "three"},
        )
        a._seq += 2
        a._out[conv.id].next_idx = 3
        a._transmit(wire.encode(bad))
        a._transmit(wire.encode(bad2))
        await conv.send(message("Ping", n=4))
        assert (await inc.next_message(5)).first.n == 4
        assert b.stats["invalid"] == 1

    with caplog.at_level(logging.WARNING):
        run(t)
    assert "holds an invalid message" in caplog.text


def test_a_broadcast_waits_for_the_listener_it_names_though_it_does_not_track_it() -> None:
    """A WC does not track lot scripts (gwc.wc.wc.WC.ignored_peers): their hellos never reach it, yet
    their acks do, and it names the lot whose run it was as a listener of its Run_Complete (heard_by),
    so that lot's ack is waited for and what the lot lost is sent again. A lot it does not name is not
    waited for."""

    async def t(make: Make, cfg: BusConfig) -> None:
        wc = await make("wc:a", ("START_RUN",), ignored=("wc:", "lot:"))
        lot = await make("lot:1", ("RUN_COMPL",), replace(cfg, faults=Faults(drop=0.3, seed=7)))
        await until(lambda: "wc:a" in lot.peers(), "the lot to hear the WC's beat")
        asked = await lot.start("START_RUN", message("Start_Run", machine_id="a", machine_run_id=1), to="wc:a")
        start = await wc.first_message(5)
        assert start is not None
        await start.send(message("Start_Run_Ack", ack_code="ACK_OK"))  # to a lot it does not track: acked
        assert (await asked.next_message(5)).first.ack_code == "ACK_OK" and "lot:1" not in wc.peers()
        for n in range(20):
            sent = await wc.start("RUN_COMPL", done(n), heard_by=("lot:1",))
            sent.end()
        got = set()
        while len(got) < 20:
            heard = await lot.first_message(5)
            assert heard is not None, f"runs {sorted(set(range(20)) - got)} never reached the lot"
            got.add(heard.first.first.machine_run_id)
            heard.end()
        await until(lambda: not wc._pending, "the lot's acks for all of them")
        assert wc.stats["gave_up"] == 0 and wc.stats["retransmitted"] > 0  # the drops were made good
        unnamed = await wc.start("RUN_COMPL", done(99))
        assert not wc._pending  # nobody it tracks listens: nothing to wait for
        unnamed.end()

    def done(n: int) -> Any:
        return message("Run_Complete", machine_id="a", machine_run_id=n, ack_code="ACK_OK")

    run(t)


def test_the_modules_of_a_host_beat_together_at_the_clocks_ticks() -> None:
    """A resting module's cost is its wake-ups: the modules of one host beat at the same ticks of the
    host's clock (docs/protocol.md, Membership), whenever each signed on."""

    async def t(make: Make, cfg: BusConfig) -> None:
        beats: dict[str, list[float]] = {"a": [], "b": []}
        a = await make("a")
        a.beat_listeners.append(lambda: beats["a"].append(time.monotonic()))
        await until(lambda: beats["a"], "a's first beat")
        await asyncio.sleep(cfg.heartbeat / 2)  # b signs on half a heartbeat after a beat of a's, on purpose
        b = await make("b")
        b.beat_listeners.append(lambda: beats["b"].append(time.monotonic()))
        await until(lambda: len(beats["a"]) >= 6 and len(beats["b"]) >= 6, "six beats each")
        gaps = [min(abs(tb - ta) for ta in beats["a"]) for tb in beats["b"][:5]]
        assert sorted(gaps)[2] < cfg.heartbeat / 5, gaps  # the median: a loaded machine may delay one

    run(t)


def test_faults_config_is_deterministic_per_module_with_a_seed() -> None:
    cfg = private_cfg(faults=Faults(drop=0.5, seed=3))
    a1 = Bus("a", cfg, logging.getLogger("x"))
    a2 = Bus("a", cfg, logging.getLogger("x"))
    b = Bus("b", cfg, logging.getLogger("x"))
    seq = [a1._faults.rng.random() for _ in range(5)]
    assert seq == [a2._faults.rng.random() for _ in range(5)]
    assert seq != [b._faults.rng.random() for _ in range(5)]


def test_a_module_never_tracks_the_peers_it_ignores_and_the_others_track_it() -> None:
    """WCs ignore each other (gwc.wc.wc.WC.ignored_peers; lot scripts ignore other lot scripts): over
    UDP the kernel drops the other WCs' beats, hellos and byes unread. The Machine Server still tracks
    both and hears what each broadcasts."""

    async def t(make: Make, cfg: BusConfig) -> None:
        a = await make("wc:a", ("PING",), ignored=("wc:",))
        b = await make("wc:b", ("PING",), ignored=("wc:",))
        ms = await make("ms", ("RUN_COMPL",))
        await known(ms, a, b)
        seen = ms.stats["beat"]
        await until(lambda: ms.stats["beat"] >= seen + 10, "five heartbeats")
        assert "wc:b" not in a.peers() and "wc:a" not in b.peers() and "ms" in a.peers()
        if TRANSPORT == "udp":
            assert a.stats["beat_ignored"] == 0 and a.stats["beat"] > 0  # dropped in the kernel
            # ... and so are its hellos on the bus port (an interest change here), not those of the others
            hellos = a.stats["hello"]
            b.set_interest(("PING", "RUN_COMPL"))
            ms.set_interest(("PING", "RUN_COMPL"))
            await until(lambda: a.stats["hello"] > hellos, "the Machine Server's hello")
            await until(lambda: ms.peers()["wc:b"].interest == {"PING", "RUN_COMPL"}, "b's hello at ms")
            assert a.stats["hello"] == hellos + 1
        conv = await a.start("RUN_COMPL", message("Run_Complete", machine_id="a", machine_run_id=1, ack_code="ACK_OK"))
        heard = await ms.first_message(5)
        assert heard is not None and heard.first.first.machine_id == "a"
        conv.end()

    run(t)


def test_a_datagram_that_breaks_the_receive_path_stops_no_heartbeat_work(caplog: Any) -> None:
    """Every datagram b opens raises (as the replay window's 2^62 shift once did): b still sends its
    beats (a keeps it), still expires the peers it no longer hears (a), and says each kind of failure
    once, counting the rest."""

    async def t(make: Make, cfg: BusConfig) -> None:
        a, b = await make("ms"), await make("msched")
        await known(a, b)

        def broken(*args: Any) -> None:
            raise MemoryError

        b._guard.open = broken  # type: ignore[method-assign]
        await until(lambda: "ms" not in b.peers(), "b to expire the peer it can no longer hear")
        await until(lambda: b.stats["failed_opening a beat"] >= 3, "three beats to fail")
        assert "msched" in a.peers()  # b's beats went on all along
        await a.start("PING", message("Ping", n=1))  # a datagram on the bus port too
        await until(lambda: b.stats["failed_handling a datagram"] >= 1, "a bus-port datagram to fail")

    with caplog.at_level(logging.ERROR):
        run(t)
    said = [r.getMessage() for r in caplog.records if r.name == "gwc.test.msched"]
    assert sum("opening a beat failed (MemoryError)" in s for s in said) == 1, said
    assert sum("handling a datagram failed (MemoryError)" in s for s in said) == 1, said
