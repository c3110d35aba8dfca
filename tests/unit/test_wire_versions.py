"""Wire versions (docs/protocol.md, "Versions"): a receiver reads every version from MIN_VERSION to
its own, the kernel filter treats them alike, a field a later version added is left out when an
older one is spoken, and a bus speaks the lowest version its live peers speak."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest

from gwc.errors import MessageError
from gwc.ipc import catalogue, wire
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.memory import MemoryTransport
from gwc.ipc.wire import Envelope
from tests.unit import test_ipc_bus_rules as rules
from tests.unit.test_ipc_bus_rules import private_cfg, until
from tests.unit.test_ipc_wire import run_filter


@pytest.fixture(autouse=True)
def keys_dir(tmp_path: Path) -> None:
    rules.KEYS_DIR = tmp_path  # private_cfg makes the bus keys there


MSG = Envelope(kind="msg", src="lot:1", inc=7, seq=1, conv="lot:1.7.1", cls="MACH_REQ", msg="Machine_Request")


def in_version(data: bytes, version: int) -> bytes:
    return data[:3] + bytes([version]) + data[4:]


def test_every_version_from_the_minimum_to_ours_is_read_and_says_which_it_is() -> None:
    data = wire.encode(MSG)
    assert data[3] == wire.VERSION and wire.decode(data).version == wire.VERSION
    for v in range(wire.MIN_VERSION, wire.VERSION + 1):
        env = wire.decode(in_version(data, v))
        assert env.version == v and env.cls == "MACH_REQ"
    for v in (wire.MIN_VERSION - 1, wire.VERSION + 1, 255):
        with pytest.raises(MessageError, match=f"unknown wire version {v} .this build reads"):
            wire.decode(in_version(data, v))


def test_an_envelope_is_encoded_in_the_version_it_names_and_no_other_we_cannot_speak() -> None:
    old = wire.encode(Envelope(kind="bye", src="msched", inc=5, version=wire.MIN_VERSION))
    assert old[3] == wire.MIN_VERSION and wire.decode(old).version == wire.MIN_VERSION
    assert old.startswith(wire.origin("msched", 5, wire.MIN_VERSION).prefix)
    with pytest.raises(MessageError, match="is not one this build speaks"):
        wire.origin("msched", 5, wire.VERSION + 1)


def test_the_kernel_filter_treats_every_version_it_reads_alike_and_keeps_the_others_for_the_log() -> None:
    code = wire.kernel_filter("msched", 5, ["MACH_REQ"])
    wanted = wire.encode(MSG)
    unwanted = wire.encode(Envelope(**{**_fields(MSG), "cls": "SETUP_RUN"}))
    own = wire.encode(Envelope(kind="hello", src="msched", inc=5))
    for v in range(wire.MIN_VERSION, wire.VERSION + 1):
        assert run_filter(code, in_version(wanted, v))
        assert not run_filter(code, in_version(unwanted, v))
        assert not run_filter(code, in_version(own, v))  # our own, whatever version we speak
    for v in (wire.MIN_VERSION - 1, wire.VERSION + 1):  # not ours to read: kept, so the bus logs it
        assert run_filter(code, in_version(unwanted, v))


def _fields(env: Envelope) -> dict[str, object]:
    return {f: getattr(env, f) for f in Envelope.__slots__}  # type: ignore[attr-defined]


def test_a_field_a_later_version_added_is_left_out_when_an_older_one_is_spoken() -> None:
    spec = catalogue._msg("Probe", note="str?@9", machine_id="str")
    assert [(f.name, f.since) for f in spec.fields] == [("note", 9), ("machine_id", 0)]
    with pytest.raises(ValueError, match="must be nullable"):
        catalogue._msg("Probe", note="str@9")
    fields = {"note": "new", "machine_id": "wc1"}
    older = wire.origin("wc:wc1", 3, wire.MIN_VERSION, {"Probe": frozenset({"note"})})
    data = wire.encode_parts(older, "msg", 1, "wc:wc1.3.1", "PING", 0, 0, 0, 0, None, "Probe", fields)
    assert wire.decode(data).fields == {"machine_id": "wc1"}  # absent: the receiver's default (None) holds
    ours = wire.origin("wc:wc1", 3)
    data = wire.encode_parts(ours, "msg", 1, "wc:wc1.3.1", "PING", 0, 0, 0, 0, None, "Probe", fields)
    assert wire.decode(data).fields == fields
    assert catalogue.fields_after(wire.VERSION) == {}  # this build's own fields are all sent at its version


def test_a_bus_speaks_the_lowest_version_of_its_live_peers_and_moves_up_when_the_oldest_leaves() -> None:
    if wire.MIN_VERSION == wire.VERSION:
        pytest.skip("this build speaks one version")
    cfg = private_cfg()

    async def main() -> None:
        def bus(name: str, interest: tuple[str, ...] = ("PING",)) -> Bus:
            return Bus(name, cfg, logging.getLogger(f"gwc.test.{name}"), interest, MemoryTransport(cfg))

        new, server = bus("hi.1"), bus("msched", ("PING", "MACH_REQ"))
        old = bus("ls")
        old._members.highest = wire.MIN_VERSION  # an older build: its hellos say so
        old.speak(wire.MIN_VERSION)
        for b in (new, server):
            await b.sign_on()
        await until(lambda: "msched" in new.peers(), "the peers to meet")
        assert new.speaking == server.speaking == wire.VERSION
        await old.sign_on()
        try:
            await until(lambda: new.speaking == server.speaking == wire.MIN_VERSION, "both to speak the older version")
            assert new.versions()["ls"] == wire.MIN_VERSION and new.versions()["msched"] == wire.VERSION
            conv = await new.start("PING", message("Ping", n=1, payload="x"))  # a broadcast in the older version
            got = await old.first_message(5)
            assert got is not None and got.first.first.name == "Ping"
            conv.end()
            got.end()
        finally:
            await old.close(flush=0.1)
        await until(lambda: new.speaking == server.speaking == wire.VERSION, "both to move up once it left")
        for b in (new, server):
            await b.close(flush=0.1)

    asyncio.run(asyncio.wait_for(main(), 30))


def test_an_untracked_sender_of_an_older_version_is_answered_in_it() -> None:
    """A WC tracks no lot script (ignored_peers), yet answers lots: one that sends in an older version
    is answered in that version while it keeps sending, and the WC moves up once it went quiet."""
    if wire.MIN_VERSION == wire.VERSION:
        pytest.skip("this build speaks one version")
    cfg = private_cfg()

    async def main() -> None:
        # (PING is not a lot class: the untracked sender is a module whose name the WC ignores.)
        wc = Bus("wc:wc1", cfg, logging.getLogger("gwc.test.wc"), ("PING",), MemoryTransport(cfg), ("hi.",))
        lot = Bus("hi.1", cfg, logging.getLogger("gwc.test.lot"), (), MemoryTransport(cfg))
        lot._members.highest = wire.MIN_VERSION
        lot.speak(wire.MIN_VERSION)
        await wc.sign_on()
        await lot.sign_on()
        try:
            await until(lambda: "wc:wc1" in lot.peers(), "the lot to know the WC")
            assert "hi.1" not in wc.peers() and wc.speaking == wire.VERSION
            conv = await lot.start("PING", message("Ping", n=1, payload="x"), to="wc:wc1")
            got = await wc.first_message(5)
            assert got is not None and wc.speaking == wire.MIN_VERSION
            await got.send(message("Pong", n=1, payload="x"))
            assert (await conv.next_message(5)).first.name == "Pong"
            conv.end()
            got.end()
        finally:
            await lot.close(flush=0.1)
        await until(lambda: wc.speaking == wire.VERSION, "the WC to move up once the lot went quiet", timeout=5)
        await wc.close(flush=0.1)

    asyncio.run(asyncio.wait_for(main(), 30))


def test_a_broadcast_an_untracked_listener_must_hear_goes_in_the_older_version_it_last_sent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A WC's Run_Complete names the lot whose run it was (heard_by), a lot the WC does not track: the
    lot may have been quiet for the whole run, longer than peer_timeout, and the WC has moved up since;
    the broadcast still goes out in the older version that lot last sent, and the lot hears it."""
    if wire.MIN_VERSION == wire.VERSION:
        pytest.skip("this build speaks one version")
    cfg = private_cfg()
    heard: list[int] = []

    async def main() -> None:
        wc = Bus("wc:wc1", cfg, logging.getLogger("gwc.test.wc"), ("PING",), MemoryTransport(cfg), ("hi.",))
        lot = Bus("hi.1", cfg, logging.getLogger("gwc.test.lot"), ("PING",), MemoryTransport(cfg))
        lot._members.highest = wire.MIN_VERSION
        lot.speak(wire.MIN_VERSION)
        decode = wire.decode

        def spy(data: bytes) -> Envelope:  # what the lot reads, in which version
            env = decode(data)
            if env.kind == "msg" and env.src == "wc:wc1":
                heard.append(env.version)
            return env

        await wc.sign_on()
        await lot.sign_on()
        try:
            await until(lambda: "wc:wc1" in lot.peers(), "the lot to know the WC")
            conv = await lot.start("PING", message("Ping", n=1, payload="x"), to="wc:wc1")
            got = await wc.first_message(5)
            assert got is not None and wc.speaking == wire.MIN_VERSION
            conv.end()
            got.end()
            await until(lambda: wc.speaking == wire.VERSION, "the WC to move up once the lot went quiet", timeout=5)
            monkeypatch.setattr(wire, "decode", spy)
            news = await wc.start("PING", message("Ping", n=2, payload="run complete"), heard_by=("hi.1",))
            told = await lot.first_message(5)
            assert told is not None and told.first is not None
            assert told.first.first.fields["n"] == 2
            assert heard == [wire.MIN_VERSION], "the broadcast was not in the version the lot last sent"
            assert wc.speaking == wire.VERSION, "one listener's version is the broadcast's, not the bus's"
            news.end()
            told.end()
        finally:
            await lot.close(flush=0.1)
            await wc.close(flush=0.1)

    asyncio.run(asyncio.wait_for(main(), 30))


def test_the_monitor_shows_a_module_restarted_on_another_build_at_its_first_hello() -> None:
    """A module restarted on a newer build signs on with a query in the oldest version it speaks, then
    beats in the version the cell speaks: `gwc monitor --members` shows what it speaks now, though its
    datagrams are in the same version as its predecessor's."""
    from gwc.hi.monitor import Versions

    shown: list[dict[str, object]] = []
    versions = Versions("CELL", shown.append)
    old = wire.VERSION - 1
    hello = Envelope(kind="hello", src="msched", inc=1, fields={wire.SPEAKS: old}, version=old)
    versions.heard(hello)
    versions.heard(hello)  # a beat: nothing changed
    assert [(r["member"], r["speaks"], r["wire"]) for r in shown] == [("msched", old, old)]
    new = {wire.SPEAKS: wire.VERSION}
    versions.heard(Envelope(kind="hello", src="msched", inc=2, fields=new, version=old, query=True))
    versions.heard(Envelope(kind="hello", src="msched", inc=2, fields=new, version=old))
    assert [(r["member"], r["speaks"], r["wire"]) for r in shown[1:]] == [("msched", wire.VERSION, old)]
