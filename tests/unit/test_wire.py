"""The wire format: round trips, compactness, and refusal of everything malformed."""

from __future__ import annotations

import random
import struct

import pytest

from gwc.errors import MessageError
from gwc.ipc import wire
from gwc.ipc.wire import Envelope

SAMPLES = [
    Envelope(kind="msg", src="lot:17", inc=99, seq=3, conv="lot:17.63.1", cls="MACH_REQ", idx=0, more=2, base=0,
             to="msched", msg="Machine_Request", fields={"entity_id": 17, "op_type": "mill", "num_machines": 2}),
    Envelope(kind="msg", src="lot:17", inc=99, seq=4, conv="lot:17.63.1", cls="MACH_REQ", idx=1, part=1,
             to="msched", msg="Machine_Entry", fields={"machine_id": "wc1"}, acks=(7, 8), to_inc=5),
    Envelope(kind="msg", src="wc:wc1", inc=2**40, seq=2**40, conv="wc:wc1.1.2", cls="RUN_COMPL", idx=7, base=7,
             msg="Run_Complete", fields={"machine_id": "wc1", "ack_code": "ACK_OK", "note": "é ✓"}),
    Envelope(kind="ack", src="msched", inc=5, to="lot:17", to_inc=99, acks=(3, 4)),
    Envelope(kind="hello", src="msched", inc=5, interest=("MACH_REQ", "STARTUP"), query=True),
    Envelope(kind="bye", src="msched", inc=5),
]


@pytest.mark.parametrize("env", SAMPLES, ids=lambda e: e.kind)
def test_round_trip(env: Envelope) -> None:
    data = wire.encode(env)
    assert data.startswith(wire.HEADER)
    assert wire.decode(data) == env


def test_the_layout_is_as_documented_and_src_inc_come_first() -> None:
    data = wire.encode(SAMPLES[-1])
    # GWC, version 2, inc, len(src), src, then kind 3 (bye) and 41 zero bytes: nothing else is set.
    assert data == b"GWC\x02" + (5).to_bytes(8, "big") + b"\x06msched" + b"\x03" + bytes(41)
    assert data.startswith(wire.own_prefix("msched", 5))
    assert not wire.encode(Envelope(kind="bye", src="msched", inc=55)).startswith(wire.own_prefix("msched", 5))
    assert not wire.own_prefix("msched2", 5).startswith(wire.own_prefix("msched", 5))
    msg = wire.encode(SAMPLES[0])
    assert msg.endswith(b'{"entity_id":17,"op_type":"mill","num_machines":2}')


def test_oversized_message_is_refused_at_the_sender_with_a_clear_error() -> None:
    env = Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping",
                   fields={"n": 1, "payload": "x" * wire.MAX_DATAGRAM})
    with pytest.raises(MessageError, match="over the bus limit.*through the database"):
        wire.encode(env)


@pytest.mark.parametrize("env", [
    Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping", fields={"n": float("nan")}),
    Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping", fields={"n": object()}),
    Envelope(kind="msg", src="a", inc=1, seq=-1, conv="a.1.1", cls="PING", msg="Ping"),
    Envelope(kind="msg", src="a", inc=1, seq=1, conv="a" * 300, cls="PING", msg="Ping"),
    Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping", to=""),
    Envelope(kind="shout", src="a", inc=1),
    Envelope(kind="bye", src="", inc=1),
], ids=["nan", "object", "negative", "long name", "empty to", "unknown kind", "empty src"])
def test_what_cannot_be_encoded_is_refused_with_message_error(env: Envelope) -> None:
    with pytest.raises(MessageError):
        wire.encode(env)


def frame(src: bytes = b"a", inc: int = 1, kind: int = 0, flags: int = 0, seq: int = 1, idx: int = 0, more: int = 0,
          part: int = 0, base: int = 0, to_inc: int = 0, conv: bytes = b"a.1.1", cls: bytes = b"PING", to: bytes = b"",
          msg: bytes = b"Ping", acks: tuple[int, ...] = (), interest: tuple[bytes, ...] = (), tail: bytes = b"",
          lengths: tuple[int, ...] | None = None) -> bytes:
    """A datagram laid out by hand (the encoder refuses to make bad ones); lengths overrides the length bytes."""
    ls, lc, lk, lt, lm = lengths or (len(src), len(conv), len(cls), len(to), len(msg))
    return (wire.HEADER + struct.pack("!QB", inc, ls) + src
            + struct.pack("!BBQIIIIQBBBBHH", kind, flags, seq, idx, more, part, base, to_inc, lc, lk, lt, lm,
                          len(acks), len(interest))
            + conv + cls + to + msg + b"".join(struct.pack("!Q", a) for a in acks)
            + b"".join(bytes([len(i)]) + i for i in interest) + tail)


def test_the_hand_made_frame_is_valid_to_begin_with() -> None:
    env = wire.decode(frame(tail=b'{"n":1}'))
    assert (env.kind, env.src, env.conv, env.cls, env.msg, env.fields) == ("msg", "a", "a.1.1", "PING", "Ping", {"n": 1})


MALFORMED = {
    "empty": b"",
    "bad magic": b"XYZ\x02" + frame()[4:],
    "old JSON version": b'GWC\x01{"k":"bye","s":"a","n":1}',
    "unknown version": b"GWC\x09" + frame()[4:],
    "truncated header": wire.HEADER + b"\0\0\0",
    "truncated fixed part": frame()[:30],
    "names past the end": frame(lengths=(1, 200, 4, 0, 4)),
    "fields not json": frame(tail=b"{nope"),
    "fields not utf-8": frame(tail=b"\xff\xfe"),
    "fields not an object": frame(tail=b"[1,2]"),
    "nesting bomb": frame(tail=b"[" * 100_000),
    "huge integer": frame(tail=b'{"n":' + b"9" * 10_000 + b"}"),
    "src not utf-8": frame(src=b"\xff"),
    "empty src": frame(src=b""),
    "unknown kind": frame(kind=9),
    "unknown flag": frame(flags=4),
    "msg without seq": frame(seq=0),
    "msg without class": frame(cls=b""),
    "follower says more": frame(idx=1, part=1, more=2),
    "base beyond idx": frame(idx=1, base=5),
    "ack of seq 0": frame(kind=1, to=b"b", to_inc=1, acks=(0,)),
    "acks past the end": frame(kind=1, to=b"b", to_inc=1, acks=(1, 2))[:-4],
    "interest past the end": frame(kind=2, interest=(b"PING",))[:-2],
    "interest not utf-8": frame(kind=2, interest=(b"\xff\xfe",)),
    "name too long": frame(kind=2, src=b"a" * 250),
    "oversized": frame(tail=b" " * wire.MAX_DATAGRAM),
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
