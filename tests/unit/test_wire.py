"""The wire format: round trips, compactness, and refusal of everything malformed."""

from __future__ import annotations

import json
import random

import pytest

from gwc.errors import MessageError
from gwc.ipc import wire
from gwc.ipc.wire import Envelope

SAMPLES = [
    Envelope(kind="msg", src="lot:17", inc=99, seq=3, conv="lot:17.63.1", cls="MACH_REQ", idx=0, more=2, base=0,
             to="msched", msg="Machine_Request", fields={"entity_id": 17, "op_type": "mill", "num_machines": 2}),
    Envelope(kind="msg", src="lot:17", inc=99, seq=4, conv="lot:17.63.1", cls="MACH_REQ", idx=1, part=1,
             to="msched", msg="Machine_Entry", fields={"machine_id": "wc1"}, acks=(7, 8), to_inc=5),
    Envelope(kind="ack", src="msched", inc=5, to="lot:17", to_inc=99, acks=(3, 4)),
    Envelope(kind="hello", src="msched", inc=5, interest=("MACH_REQ", "STARTUP"), query=True),
    Envelope(kind="bye", src="msched", inc=5),
]


@pytest.mark.parametrize("env", SAMPLES, ids=lambda e: e.kind)
def test_round_trip(env: Envelope) -> None:
    data = wire.encode(env)
    assert data.startswith(wire.HEADER)
    assert wire.decode(data) == env


def test_defaults_are_left_out_and_src_inc_come_first() -> None:
    data = wire.encode(SAMPLES[4])
    assert json.loads(data[4:]) == {"s": "msched", "n": 5, "k": "bye"}
    assert data.startswith(wire.own_prefix("msched", 5))
    assert not wire.encode(Envelope(kind="bye", src="msched", inc=55)).startswith(wire.own_prefix("msched", 5))


def test_oversized_message_is_refused_at_the_sender_with_a_clear_error() -> None:
    env = Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping",
                   fields={"n": 1, "payload": "x" * wire.MAX_DATAGRAM})
    with pytest.raises(MessageError, match="over the bus limit.*through the database"):
        wire.encode(env)


def body(**keys: object) -> bytes:
    return wire.HEADER + json.dumps(keys).encode()


MALFORMED = {
    "empty": b"",
    "bad magic": b"XYZ\x01{}",
    "unknown version": b"GWC\x09" + body(k="bye", s="a", n=1)[4:],
    "not json": wire.HEADER + b"{nope",
    "not utf-8": wire.HEADER + b"\xff\xfe",
    "not an object": wire.HEADER + b"[1,2]",
    "nesting bomb": wire.HEADER + b"[" * 100_000,
    "huge integer": wire.HEADER + b'{"k":"bye","s":"a","n":' + b"9" * 10_000 + b"}",
    "missing src": body(k="bye", n=1),
    "empty src": body(k="bye", s="", n=1),
    "unknown kind": body(k="shout", s="a", n=1),
    "unknown key": body(k="bye", s="a", n=1, z=1),
    "bool as int": body(k="bye", s="a", n=True),
    "negative": body(k="msg", s="a", n=1, q=1, c="a.1.1", C="PING", m="Ping", i=-1),
    "msg without seq": body(k="msg", s="a", n=1, c="a.1.1", C="PING", m="Ping"),
    "follower says more": body(k="msg", s="a", n=1, q=1, c="a.1.1", C="PING", m="Ping", i=1, p=1, **{"+": 2}),
    "base beyond idx": body(k="msg", s="a", n=1, q=1, c="a.1.1", C="PING", m="Ping", i=1, b=5),
    "acks not ints": body(k="ack", s="a", n=1, t="b", T=1, a=["x"]),
    "interest not strings": body(k="hello", s="a", n=1, I=[1]),
    "name too long": body(k="hello", s="a" * 1000, n=1),
    "oversized": wire.HEADER + b" " * wire.MAX_DATAGRAM,
}


@pytest.mark.parametrize("data", MALFORMED.values(), ids=MALFORMED.keys())
def test_malformed_datagrams_raise_message_error(data: bytes) -> None:
    with pytest.raises(MessageError):
        wire.decode(data)


def test_random_mutations_never_raise_anything_but_message_error() -> None:
    rnd = random.Random(7)
    valid = [wire.encode(e) for e in SAMPLES]
    for _ in range(5000):
        data = bytearray(rnd.choice(valid))
        for _ in range(rnd.randrange(1, 4)):
            data[rnd.randrange(len(data))] = rnd.randrange(256)
        try:
            wire.decode(bytes(data[: rnd.randrange(1, len(data) + 1)]))
        except MessageError:
            pass
