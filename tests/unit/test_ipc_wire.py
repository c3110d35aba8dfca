"""The wire format: round trips, compactness, and refusal of everything malformed."""

from __future__ import annotations

import random
import struct
import zlib

import pytest

from gwc.errors import MessageError
from gwc.ipc import wire
from gwc.ipc.wire import Envelope

SAMPLES = [
    Envelope(
        kind="msg",
        src="lot:17",
        inc=99,
        seq=3,
        conv="lot:17.63.1",
        cls="MACH_REQ",
        idx=0,
        more=2,
        base=0,
        to="msched",
        msg="Machine_Request",
        fields={"entity_id": 17, "op_type": "mill", "num_machines": 2},
    ),
    Envelope(
        kind="msg",
        src="lot:17",
        inc=99,
        seq=4,
        conv="lot:17.63.1",
        cls="MACH_REQ",
        idx=1,
        part=1,
        to="msched",
        msg="Machine_Entry",
        fields={"machine_id": "wc1"},
        acks=(7, 8),
        to_inc=5,
    ),
    Envelope(
        kind="msg",
        src="wc:wc1",
        inc=2**40,
        seq=2**40,
        conv="wc:wc1.1.2",
        cls="RUN_COMPL",
        idx=7,
        base=7,
        msg="Run_Complete",
        fields={"machine_id": "wc1", "ack_code": "ACK_OK", "note": "é ✓"},
        subject="wc1",
    ),
    Envelope(kind="ack", src="msched", inc=5, to="lot:17", to_inc=99, acks=(3, 4)),
    Envelope(kind="hello", src="msched", inc=5, interest=("MACH_REQ", "STARTUP"), query=True),
    Envelope(
        kind="hello",
        src="lot:17",
        inc=99,
        interest=("MOD_DIED",),
        subjects=(("RUN_COMPL", "wc1"), ("RUN_COMPL", "wc2"), ("UPD_ME_ST", "wc1")),
    ),
    Envelope(kind="bye", src="msched", inc=5),
]


@pytest.mark.parametrize("env", SAMPLES, ids=lambda e: e.kind)
def test_round_trip(env: Envelope) -> None:
    data = wire.encode(env)
    assert data.startswith(wire.HEADER)
    assert wire.decode(data) == env


def test_the_layout_is_as_documented_and_the_sender_comes_first() -> None:
    data = wire.encode(SAMPLES[-1])
    # GWC, version 5, inc, src tag, no to, cls or subject tag, kind 3 (bye), 33 zero bytes, len(src) 6,
    # 9 zero bytes, src.
    src_tag = (zlib.crc32(b"msched") | 1).to_bytes(4, "big")
    assert data == (
        b"GWC\x05" + (5).to_bytes(8, "big") + src_tag + bytes(12) + b"\x03" + bytes(33) + b"\x06" + bytes(9) + b"msched"
    )
    assert data.startswith(wire.origin("msched", 5).prefix)
    assert not wire.encode(Envelope(kind="bye", src="msched", inc=55)).startswith(wire.origin("msched", 5).prefix)
    assert not wire.origin("msched2", 5).prefix.startswith(wire.origin("msched", 5).prefix)
    msg = wire.encode(SAMPLES[0])
    assert msg.endswith(b'{"entity_id":17,"op_type":"mill","num_machines":2}')


def test_oversized_message_is_refused_at_the_sender_with_a_clear_error() -> None:
    env = Envelope(
        kind="msg",
        src="a",
        inc=1,
        seq=1,
        conv="a.1.1",
        cls="PING",
        msg="Ping",
        fields={"n": 1, "payload": "x" * wire.MAX_DATAGRAM},
    )
    with pytest.raises(MessageError, match="over the bus limit.*through the database"):
        wire.encode(env)


@pytest.mark.parametrize(
    "env",
    [
        Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping", fields={"n": float("nan")}),
        Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping", fields={"n": object()}),
        Envelope(kind="msg", src="a", inc=1, seq=-1, conv="a.1.1", cls="PING", msg="Ping"),
        Envelope(kind="msg", src="a", inc=1, seq=1, conv="a" * 300, cls="PING", msg="Ping"),
        Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping", to=""),
        Envelope(kind="shout", src="a", inc=1),
        Envelope(kind="bye", src="", inc=1),
    ],
    ids=["nan", "object", "negative", "long name", "empty to", "unknown kind", "empty src"],
)
def test_what_cannot_be_encoded_is_refused_with_message_error(env: Envelope) -> None:
    with pytest.raises(MessageError):
        wire.encode(env)


def frame(
    src: bytes = b"a",
    inc: int = 1,
    kind: int = 0,
    flags: int = 0,
    seq: int = 1,
    idx: int = 0,
    more: int = 0,
    part: int = 0,
    base: int = 0,
    to_inc: int = 0,
    conv: bytes = b"a.1.1",
    cls: bytes = b"PING",
    to: bytes = b"",
    msg: bytes = b"Ping",
    acks: tuple[int, ...] = (),
    interest: tuple[bytes, ...] = (),
    tail: bytes = b"",
    lengths: tuple[int, ...] | None = None,
    subject: bytes = b"",
) -> bytes:
    """A datagram laid out by hand (the encoder refuses to make bad ones); lengths overrides the length bytes.
    An interest entry is a class, or b"CLASS/subject"."""
    ls, lc, lk, lt, lm, lj = lengths or (len(src), len(conv), len(cls), len(to), len(msg), len(subject))
    tags = [zlib.crc32(name) | 1 if name else 0 for name in (src, to, cls, subject)]
    entries = [i.partition(b"/")[::2] for i in interest]
    return (
        wire.HEADER
        + struct.pack(
            "!QIIIIBBQIIIIQBBBBBBHH",
            inc,
            *tags,
            kind,
            flags,
            seq,
            idx,
            more,
            part,
            base,
            to_inc,
            ls,
            lc,
            lk,
            lt,
            lm,
            lj,
            len(acks),
            len(interest),
        )
        + src
        + conv
        + cls
        + to
        + msg
        + subject
        + b"".join(struct.pack("!Q", a) for a in acks)
        + b"".join(bytes([len(c)]) + c + bytes([len(j)]) + j for c, j in entries)
        + tail
    )


def test_the_hand_made_frame_is_valid_to_begin_with() -> None:
    env = wire.decode(frame(tail=b'{"n":1}'))
    assert (env.kind, env.src, env.conv, env.cls, env.msg, env.fields) == (
        "msg",
        "a",
        "a.1.1",
        "PING",
        "Ping",
        {"n": 1},
    )


MALFORMED = {
    "empty": b"",
    "bad magic": b"XYZ\x02" + frame()[4:],
    "old JSON version": b'GWC\x01{"k":"bye","s":"a","n":1}',
    "unknown version": b"GWC\x09" + frame()[4:],
    "truncated header": wire.HEADER + b"\0\0\0",
    "truncated fixed part": frame()[:30],
    "names past the end": frame(lengths=(1, 200, 4, 0, 4, 0)),
    "fields not json": frame(tail=b"{nope"),
    "fields not utf-8": frame(tail=b"\xff\xfe"),
    "fields not an object": frame(tail=b"[1,2]"),
    "nesting bomb": frame(tail=b"[" * 100_000),
    "huge integer": frame(tail=b'{"n":' + b"9" * 10_000 + b"}"),
    "src not utf-8": frame(src=b"\xff"),
    "empty src": frame(src=b""),
    "wrong src tag": frame()[:12] + b"\0\0\0\1" + frame()[16:],
    "wrong addressee tag": frame(to=b"b")[:16] + b"\0\0\0\0" + frame(to=b"b")[20:],
    "wrong class tag": frame()[:20] + b"\0\0\0\3" + frame()[24:],
    "unknown kind": frame(kind=9),
    "unknown flag": frame(flags=4),
    "msg without seq": frame(seq=0),
    "msg without class": frame(cls=b""),
    "follower says more": frame(idx=1, part=1, more=2),
    "base beyond idx": frame(idx=1, base=5),
    "ack of seq 0": frame(kind=1, to=b"b", to_inc=1, acks=(0,)),
    "acks past the end": frame(kind=1, to=b"b", to_inc=1, acks=(1, 2))[:-4],
    "interest past the end": frame(kind=2, interest=(b"PING",))[:-2],
    "interest's subject missing": frame(kind=2, interest=(b"PING",))[:-1],
    "interest's subject past the end": frame(kind=2, interest=(b"RUN_COMPL/wc1",))[:-1],
    "interest not utf-8": frame(kind=2, interest=(b"\xff\xfe",)),
    "interest's subject not utf-8": frame(kind=2, interest=(b"RUN_COMPL/\xff\xfe",)),
    "wrong subject tag": frame(subject=b"wc1")[:24] + b"\0\0\0\5" + frame(subject=b"wc1")[28:],
    "subject with a NUL": frame(subject=b"w\0c"),
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


def run_filter(code: list[tuple[int, int, int, int]], payload: bytes) -> bool:
    """Classic BPF, as much of it as wire.kernel_filter uses, run as Linux runs it on a UDP socket."""
    packet = bytes(wire.UDP_HEADER) + payload
    a = x = pc = 0
    while True:
        op, jt, jf, k = code[pc]
        pc += 1
        if op == 0x80:
            a = len(packet)
        elif op in (0x20, 0x30):  # ld word / byte, absolute; out of the packet: drop
            size = 4 if op == 0x20 else 1
            if k + size > len(packet):
                return False
            a = int.from_bytes(packet[k : k + size], "big")
        elif op == 0x07:
            x = a
        elif op == 0x1C:
            a = (a - x) & 0xFFFF_FFFF
        elif op in (0x15, 0x35):
            pc += jt if (a == k if op == 0x15 else a >= k) else jf
        elif op == 0x06:
            return k != 0
        else:
            raise AssertionError(f"unexpected opcode {op:#x}")


def test_the_kernel_filter_keeps_exactly_what_the_module_would_read() -> None:
    code = wire.kernel_filter("msched", 5, ["MACH_REQ", "STARTUP"])

    def kept(**kw: object) -> bool:
        return run_filter(code, wire.encode(Envelope(**kw)))  # type: ignore[arg-type]

    msg = dict(kind="msg", src="lot:1", inc=7, seq=1, conv="lot:1.7.1", msg="Machine_Request")
    assert kept(**msg, cls="MACH_REQ")  # a broadcast opener of a class it listens to
    assert kept(**msg, cls="MACH_REQ", idx=1, part=1)  # the rest of that opening batch
    assert not kept(**msg, cls="SETUP_RUN")  # ... of a class it does not
    assert not kept(**msg, cls="SETUP_RUN", idx=2, part=2, more=0)
    assert kept(**msg, cls="SETUP_RUN", idx=3, base=3)  # a later batch: it may hold the conversation
    assert kept(**msg, cls="SETUP_RUN", to="msched")  # directed to it, whatever its interest
    assert not kept(**msg, cls="MACH_REQ", to="wc:wc1")  # directed to another
    assert kept(kind="ack", src="wc:wc1", inc=3, to="msched", to_inc=5, acks=(1,))
    assert not kept(kind="ack", src="wc:wc1", inc=3, to="lot:1", to_inc=7, acks=(1,))
    assert kept(kind="hello", src="wc:wc1", inc=3) and kept(kind="bye", src="wc:wc1", inc=3)
    assert kept(kind="hello", src="wc:wc1", inc=3, to="msched")  # an answer to its query
    assert not kept(kind="hello", src="wc:wc1", inc=3, to="lot:1")  # ... to another's
    assert not kept(kind="hello", src="msched", inc=5)  # its own, looped back
    assert not kept(**dict(msg, src="msched", inc=5), cls="MACH_REQ")
    assert kept(kind="hello", src="msched", inc=6)  # its restarted self, or another process of that name
    assert kept(kind="hello", src="msched2", inc=5)
    for garbage in (b"", b"GWC", b"GWC\x02" + bytes(80), bytes(range(200))):  # the bus logs what is malformed
        assert run_filter(code, garbage)


def test_the_kernel_filter_drops_the_hellos_and_byes_of_ignored_modules() -> None:
    code = wire.kernel_filter("lot:7", 5, ["RUN_COMPL"], ignored=("lot:",))

    def kept(**kw: object) -> bool:
        return run_filter(code, wire.encode(Envelope(**kw)))  # type: ignore[arg-type]

    for kind in ("hello", "bye"):
        assert not kept(kind=kind, src="lot:12", inc=3)  # another lot's sign-on, interest change, bye
        assert not kept(kind=kind, src="lot:", inc=3)
        assert kept(kind=kind, src="wc:wc1", inc=3) and kept(kind=kind, src="lot", inc=3)
        assert kept(kind=kind, src="lotx:1", inc=3) and kept(kind=kind, src="msched", inc=3)
    assert not kept(kind="hello", src="lot:12", inc=3, query=True)  # not answered: not even read
    assert kept(kind="hello", src="msched", inc=3, to="lot:7")  # an answer to its own query
    msg = dict(kind="msg", inc=3, seq=1, msg="Run_Complete", cls="RUN_COMPL")
    assert kept(**msg, src="wc:wc1", conv="wc:wc1.3.1")  # msgs go by interest, whoever sends them
    assert kept(**msg, src="lot:12", conv="lot:12.3.1")
    assert kept(kind="ack", src="wc:wc1", inc=3, to="lot:7", to_inc=5, acks=(1,))
    assert kept(kind="ack", src="lot:12", inc=3, to="lot:7", to_inc=5, acks=(1,))  # an ignored module's ack to it
    assert not kept(kind="ack", src="lot:12", inc=3, to="lot:8", to_inc=5, acks=(1,))
    unfiltered = wire.kernel_filter("lot:7", 5, ["RUN_COMPL"])
    assert run_filter(unfiltered, wire.encode(Envelope(kind="hello", src="lot:12", inc=3)))


def test_the_kernel_filter_of_a_wc_drops_the_membership_of_both_prefixes_it_ignores() -> None:
    code = wire.kernel_filter("wc:a", 5, ["SETUP_RUN"], ignored=("wc:", "lot:"))

    def kept(**kw: object) -> bool:
        return run_filter(code, wire.encode(Envelope(**kw)))  # type: ignore[arg-type]

    for src in ("wc:b", "lot:12"):
        for kind in ("hello", "bye"):
            assert not kept(kind=kind, src=src, inc=3), (kind, src)
        assert kept(kind="ack", src=src, inc=3, to="wc:a", to_inc=5, acks=(1,))  # acks to it: kept
        assert kept(kind="msg", src=src, inc=3, seq=1, conv=f"{src}.3.1", cls="SETUP_RUN", msg="Setup_Run", to="wc:a")
    for src in ("ms", "msched", "lot", "wc", "lotx:1"):
        assert kept(kind="hello", src=src, inc=3) and kept(kind="bye", src=src, inc=3), src


def test_the_beat_filter_drops_exactly_the_beats_of_the_ignored_modules() -> None:
    code = wire.beat_filter(("wc:",))

    def kept(src: str) -> bool:
        return run_filter(code, wire.encode(Envelope(kind="hello", src=src, inc=3, interest=("SETUP_RUN",))))

    assert not kept("wc:wc1") and not kept("wc:a")
    assert kept("ms") and kept("msched") and kept("lot:12") and kept("wc") and kept("wcx:1") and kept("w")
    for garbage in (b"", b"GWC", bytes(60)):  # too short to tell: the bus counts it
        assert run_filter(code, garbage)


def test_the_kernel_filter_keeps_of_a_narrowed_class_only_what_is_about_its_subjects() -> None:
    code = wire.kernel_filter(
        "lot:7", 5, ["MOD_DIED"], ignored=("lot:",), subjects={"RUN_COMPL": ["wc1", "wc3"], "UPD_ME_ST": ["wc1"]}
    )

    def kept(**kw: object) -> bool:
        return run_filter(code, wire.encode(Envelope(**kw)))  # type: ignore[arg-type]

    news = dict(kind="msg", inc=3, seq=1, idx=0)
    assert kept(**news, src="wc:wc1", conv="wc:wc1.3.1", cls="RUN_COMPL", msg="Run_Complete", subject="wc1")
    assert kept(**news, src="wc:wc3", conv="wc:wc3.3.1", cls="RUN_COMPL", msg="Run_Complete", subject="wc3")
    assert not kept(**news, src="wc:wc2", conv="wc:wc2.3.1", cls="RUN_COMPL", msg="Run_Complete", subject="wc2")
    assert not kept(**news, src="wc:wc2", conv="wc:wc2.3.1", cls="RUN_COMPL", msg="Run_Complete")  # none named
    assert kept(**news, src="ms", conv="ms.3.1", cls="UPD_ME_ST", msg="Update_ME_Status", subject="wc1")
    assert not kept(**news, src="ms", conv="ms.3.1", cls="UPD_ME_ST", msg="Update_ME_Status", subject="wc3")
    assert kept(**news, src="agent", conv="agent.3.1", cls="MOD_DIED", msg="Module_Died")  # a class heard whole
    assert kept(**news, src="agent", conv="agent.3.1", cls="MOD_DIED", msg="Module_Died", subject="wc2")
    assert not kept(**news, src="ms", conv="ms.3.1", cls="ALARM_CLE", msg="Alarm_Clear", subject="wc1")
    assert kept(**news, src="ms", conv="ms.3.1", cls="UPD_ME_ST", msg="Update_ME_Status", subject="wc2", to="lot:7")


def test_a_class_heard_whole_and_about_subjects_is_heard_whole_and_many_subjects_fit_the_filter() -> None:
    code = wire.kernel_filter("lot:7", 5, ["RUN_COMPL"], subjects={"RUN_COMPL": ["wc1"]})
    env = dict(kind="msg", src="wc:wc2", inc=3, seq=1, conv="wc:wc2.3.1", cls="RUN_COMPL", msg="Run_Complete")
    assert run_filter(code, wire.encode(Envelope(**env, subject="wc2")))  # type: ignore[arg-type]
    machines = [f"wc{i}" for i in range(200)]  # past what 8-bit jumps reach: the kernel keeps the class whole
    code = wire.kernel_filter("lot:7", 5, [], subjects={"RUN_COMPL": machines, "UPD_ME_ST": machines[:30]})
    assert run_filter(code, wire.encode(Envelope(**env, subject="wc199")))  # type: ignore[arg-type]
    code = wire.kernel_filter("lot:7", 5, [], subjects={"RUN_COMPL": machines[:32], "UPD_ME_ST": machines[:32]})
    assert run_filter(code, wire.encode(Envelope(**env, subject="wc31")))  # type: ignore[arg-type]
    assert not run_filter(code, wire.encode(Envelope(**env, subject="wc32")))  # type: ignore[arg-type]
