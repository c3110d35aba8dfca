"""The bus wire format: one UDP datagram = a binary header + the message's fields as one JSON object.

Kept apart from the bus (as python-can keeps encoding apart from its transports) so that the
monitor, the fuzz tests and a client in another language share one definition. docs/protocol.md
is the normative description; this module is its reference implementation.

The envelope (who, which conversation, numbering, acks) is fixed-layout binary, read with one
struct call; only the application's fields are JSON. Every datagram is decoded and every msg
encoded on the bus's hot path, and a JSON envelope cost several times the rest of the work there.

The fixed part begins with the *filter keys* (the sender's incarnation and 32-bit tags of the
sender, the addressee and the class) at fixed offsets, so that the kernel can drop, before any
process wakes, what a module would drop anyway: `kernel_filter` builds that program.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from gwc.errors import MessageError

MAGIC = b"GWC"
# Wire versions (docs/protocol.md, "Versions"): this build encodes in any version from MIN_VERSION to
# VERSION and decodes all of them; a bus speaks the lowest version its live peers speak (gwc/ipc/
# membership.py), so that a cell being upgraded host by host goes on talking. Versions 4 and 5 share
# one layout: 5 adds `speaks` to the hello's fields and the rules of negotiation.
VERSION = 5
MIN_VERSION = 4
HEADER = MAGIC + bytes([VERSION])
SPEAKS = "speaks"  # the hello field naming the highest version its sender speaks (absent: the datagram's)
MAX_DATAGRAM = 60_000  # below the 65,507-byte UDP limit, with room for IP options
MAX_NAME = 200  # bytes: module names, conversation ids and class names are short; longer is hostile

KINDS = ("msg", "ack", "hello", "bye")
_KIND_CODE = {kind: code for code, kind in enumerate(KINDS)}
QUERY = 1  # flags bit: hello asks every member to answer with its own hello


@dataclass(slots=True)
class Envelope:
    """Everything one datagram carries. Which fields matter depends on kind (see docs/protocol.md).

    Not frozen, for speed on the hot path (a frozen dataclass's __init__ costs microseconds);
    treat it as a value all the same: change it with dataclasses.replace().
    """

    kind: str
    src: str  # sender's module name on the bus, e.g. "msched", "wc:cmm_wc", "lot:17"
    inc: int  # sender's incarnation: random per process start, so a restart is a new sender
    seq: int = 0  # msg: per-(src, inc) datagram number, echoed by acks
    conv: str = ""  # msg: conversation id, "<initiator>.<inc hex>.<n>"
    cls: str = ""  # msg: conversation class, e.g. "MACH_REQ"
    idx: int = 0  # msg: index of this message among those src sent in conv (0, 1, 2, ...)
    more: int = 0  # msg: on the first message of a batch, how many messages of the batch follow it
    part: int = 0  # msg: position in its batch (0 = the first message, which carries `more`)
    base: int = 0  # msg: every message src sent in conv with idx < base is settled (see docs/protocol.md)
    to: str | None = None  # msg/ack: addressee module name; None = everyone interested in cls
    msg: str = ""  # msg: message class, e.g. "Machine_Request"
    fields: dict[str, Any] = field(default_factory=dict)
    acks: tuple[int, ...] = ()  # ack (or msg, piggybacked): the seqs of `to` acknowledged
    to_inc: int = 0  # ack (or msg carrying acks): the incarnation of the addressee
    interest: tuple[str, ...] = ()  # hello: classes src listens to now
    query: bool = False  # hello: "tell me who you are" (peers answer with their own hello)
    subject: str = ""  # msg: what it is about, for a class that names one (UPD_ME_ST, RUN_COMPL: the machine)
    subjects: tuple[tuple[str, str], ...] = ()  # hello: (class, subject): src hears that class about these only
    version: int = VERSION  # the wire version it is (to be) encoded in: decode sets it from the datagram


# After HEADER, the fixed part: inc, the tags of src, to, cls and subject, kind, flags, seq, idx, more, part,
# base, to_inc, the lengths of src, conv, cls, to, msg and subject, the number of acks and of interest
# entries. Network order.
_FIXED = struct.Struct("!QIIIIBBQIIIIQBBBBBBHH")
_AFTER_PREFIX = struct.Struct("!" + _FIXED.format[3:])  # the fixed part after inc and src tag (Origin.prefix)
_BODY = len(HEADER) + _FIXED.size  # where the strings begin
BODY_OFFSET = _BODY
SRC_LEN_OFFSET = len(HEADER) + struct.calcsize("!QIIIIBBQIIIIQ")  # the byte giving the length of src
# Offsets in the datagram of what the kernel filter reads (docs/protocol.md, "Kernel filtering").
OFF_INC, OFF_SRC_TAG, OFF_TO_TAG, OFF_CLS_TAG, OFF_SUBJ_TAG, OFF_KIND, OFF_IDX, OFF_PART = 4, 12, 16, 20, 24, 28, 38, 46


def tag(name: str | bytes) -> int:
    """The 32-bit filter key of a name: its CRC-32 (zlib's) with the low bit set, so that 0 means none."""
    return zlib.crc32(name.encode() if isinstance(name, str) else name) | 1


# The few names a module meets (modules, classes) recur on every datagram: their encodings and tags are
# remembered, not recomputed. Bounded, since names come from the network: emptied when full.
_MAX_CACHED = 4096
_NONE = {b"": ("", 0)}  # no name: tag 0
_DECODED: dict[bytes, tuple[str, int]] = dict(_NONE)  # UTF-8 -> (name, tag)
_ENCODED: dict[str, tuple[bytes, int]] = {}  # name -> (UTF-8, tag)


def _decoded(b: bytes) -> tuple[str, int]:
    got = _DECODED.get(b)
    if got is None:
        got = (b.decode(), zlib.crc32(b) | 1)
        if len(_DECODED) >= _MAX_CACHED:
            _DECODED.clear()
            _DECODED.update(_NONE)
        _DECODED[b] = got
    return got


_U64S: dict[int, struct.Struct] = {}  # "!nQ" per count n of acks met: up to the 1000 a sender puts in one


def _u64s(n: int) -> struct.Struct:
    s = _U64S.get(n)
    if s is None:
        s = struct.Struct(f"!{n}Q")
        if n <= 1000:
            _U64S[n] = s
    return s


def _encoded(name: str) -> tuple[bytes, int]:
    got = _ENCODED.get(name)
    if got is None:
        b = name.encode()
        got = (b, zlib.crc32(b) | 1)
        if len(_ENCODED) >= _MAX_CACHED:
            _ENCODED.clear()
        _ENCODED[name] = got
    return got


_ENCODER = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False, allow_nan=False)
_dumps = _ENCODER.encode
# The C encoder and scanner behind json.dumps/json.loads, called directly: the Python layers around
# them (a new encoder object per call, whitespace regexes) cost more than the work on a small object.
# No circular-reference bookkeeping: a cyclic value ends in RecursionError, refused like any other.
_c_make_encoder: Any = getattr(json.encoder, "c_make_encoder", None)
_c_encode = (
    _c_make_encoder(None, _ENCODER.default, json.encoder.encode_basestring, None, ":", ",", False, False, False)
    if _c_make_encoder
    else None
)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a value the bus carries")


def _finite(text: str) -> float:
    value = float(text)
    if value in (INF, -INF):  # 1e999: JSON has no infinity, and float() makes one of it
        raise ValueError(f"number {text[:20]} is out of range")
    return value


INF = float("inf")
# NaN and Infinity are not JSON: Python's decoder takes them by default, the bus does not.
_scan = json.JSONDecoder(parse_constant=_no_constant, parse_float=_finite).scan_once  # type: ignore[attr-defined]
_json_loads = json.JSONDecoder(parse_constant=_no_constant, parse_float=_finite).decode


def _json(value: Any) -> str:
    return "".join(_c_encode(value, 0)) if _c_encode else _dumps(value)


@dataclass(frozen=True, slots=True)
class Origin:
    """What every datagram of one sender (module name, incarnation) begins with, computed once, and
    how it encodes for the wire version it speaks."""

    src: bytes
    prefix: bytes  # magic, version, inc, src tag: lets the sender skip its own looped-back datagrams
    version: int = VERSION
    # Message fields a peer of `version` does not know (catalogue.fields_after): left out of each
    # msg of those message classes, so that an older receiver finds them absent, as it expects.
    omit: Mapping[str, frozenset[str]] | None = None


def check_version(version: int) -> int:
    """`version` if this build can encode it, else MessageError."""
    if not MIN_VERSION <= version <= VERSION:
        raise MessageError(f"wire version {version} is not one this build speaks ({MIN_VERSION}..{VERSION})")
    return version


def origin(src: str, inc: int, version: int = VERSION, omit: Mapping[str, frozenset[str]] | None = None) -> Origin:
    name = src.encode()
    if not 0 < len(name) <= MAX_NAME:
        raise MessageError(f"module name {src[:40]!r} must be 1 to {MAX_NAME} bytes")
    check_version(version)
    try:
        return Origin(name, MAGIC + bytes([version]) + struct.pack("!QI", inc, tag(name)), version, omit or None)
    except struct.error:
        raise MessageError(f"incarnation {inc} out of range") from None


def encode(env: Envelope) -> bytes:
    """Serialise one envelope; refuse what cannot fit one datagram (or the layout)."""
    return encode_parts(
        origin(env.src, env.inc, env.version),
        env.kind,
        env.seq,
        env.conv,
        env.cls,
        env.idx,
        env.more,
        env.part,
        env.base,
        env.to,
        env.msg,
        env.fields,
        env.subject,
        env.acks,
        env.to_inc,
        env.interest,
        env.query,
        env.subjects,
    )


def encode_parts(
    orig: Origin,
    kind: str,
    seq: int,
    conv: str,
    cls: str,
    idx: int,
    more: int,
    part: int,
    base: int,
    to: str | None,
    msg: str,
    fields: dict[str, Any],
    subject: str = "",
    acks: Iterable[int] = (),
    to_inc: int = 0,
    interest: Iterable[str] = (),
    query: bool = False,
    subjects: Iterable[tuple[str, str]] = (),
) -> bytes:
    """encode() from the parts, for the bus's hot path (no Envelope made just to be read).

    orig is origin(src, inc, version) of the sender.
    """
    if orig.omit is not None and msg in orig.omit:  # speaking an older version: its fields only
        gone = orig.omit[msg]
        fields = {k: v for k, v in fields.items() if k not in gone}
    c = conv.encode()
    k, ktag = _ENCODED.get(cls) or _encoded(cls)
    m = (_ENCODED.get(msg) or _encoded(msg))[0]
    if to is None:
        t, ttag = b"", 0
    else:
        t, ttag = _ENCODED.get(to) or _encoded(to)
        if not t:
            raise MessageError("the addressee of a datagram cannot be empty (None: everyone)")
    j, jtag = _ENCODED.get(subject) or _encoded(subject) if subject else (b"", 0)
    if len(c) > MAX_NAME or len(k) > MAX_NAME or len(t) > MAX_NAME or len(m) > MAX_NAME or len(j) > MAX_NAME:
        raise MessageError(f"{msg or kind} in {conv or '-'}: a name is over {MAX_NAME} bytes")
    src = orig.src
    parts = [orig.prefix, b"", src, c, k, t, m, j]  # parts[1]: the rest of the fixed part, packed last
    acks = tuple(acks)
    entries: list[tuple[str, str]] = []
    if interest or subjects:  # hellos only: a msg makes no list
        entries += ((cl, "") for cl in interest)
        entries += subjects
    try:
        if acks:
            if 0 in acks:
                raise MessageError("acks must be positive integers")
            parts.append(_u64s(len(acks)).pack(*acks))
        for cl, about in entries:
            name, sub = cl.encode(), about.encode()
            if not 0 < len(name) <= MAX_NAME or len(sub) > MAX_NAME:
                raise MessageError(
                    f"interest entry {cl[:40]!r} {about[:40]!r}: a name is empty or over {MAX_NAME} bytes"
                )
            parts += (bytes([len(name)]), name, bytes([len(sub)]), sub)
        if fields:
            parts.append(_json(fields).encode())
        parts[1] = _AFTER_PREFIX.pack(
            ttag,
            ktag if k else 0,
            jtag,
            _KIND_CODE[kind],
            QUERY if query else 0,
            seq,
            idx,
            more,
            part,
            base,
            to_inc,
            len(src),
            len(c),
            len(k),
            len(t),
            len(m),
            len(j),
            len(acks),
            len(entries),
        )
    except MessageError:
        raise
    except (TypeError, ValueError, RecursionError, KeyError, struct.error) as e:
        raise MessageError(f"{msg or kind} in {conv or '-'} cannot be encoded: {e}") from None
    data = b"".join(parts)
    if len(data) > MAX_DATAGRAM:
        raise _oversize(msg or kind, conv, len(data))
    return data


def _oversize(what: str, conv: str, size: int) -> MessageError:
    return MessageError(
        f"{what} in {conv or '-'} is {size} bytes, over the bus limit of "
        f"{MAX_DATAGRAM}: send large payloads (recipes, results) through the database, not the bus"
    )


def encode_msg(
    orig: Origin,
    seq: int,
    conv: str,
    cls: str,
    idx: int,
    more: int,
    part: int,
    base: int,
    to: str | None,
    msg: str,
    fields: dict[str, Any],
    subject: str = "",
    acks: tuple[int, ...] | list[int] = (),
    to_inc: int = 0,
) -> bytes:
    """encode_parts() of a msg, the bus's hot path: the same bytes, without a hello's interest entries
    and the checks only they need (docs/performance.md, "The bus")."""
    if orig.omit is not None and msg in orig.omit:  # speaking an older version: its fields only
        gone = orig.omit[msg]
        fields = {k: v for k, v in fields.items() if k not in gone}
    cached = _ENCODED
    c = conv.encode()
    k, ktag = cached.get(cls) or _encoded(cls)
    m = (cached.get(msg) or _encoded(msg))[0]
    if to is None:
        t, ttag = b"", 0
    else:
        t, ttag = cached.get(to) or _encoded(to)
        if not t:
            raise MessageError("the addressee of a datagram cannot be empty (None: everyone)")
    j, jtag = cached.get(subject) or _encoded(subject) if subject else (b"", 0)
    lc, lk, lt, lm, lj = len(c), len(k), len(t), len(m), len(j)
    if lc > MAX_NAME or lk > MAX_NAME or lt > MAX_NAME or lm > MAX_NAME or lj > MAX_NAME:
        raise MessageError(f"{msg or 'msg'} in {conv or '-'}: a name is over {MAX_NAME} bytes")
    src = orig.src
    na = len(acks)
    try:
        head = _AFTER_PREFIX.pack(
            ttag, ktag if k else 0, jtag, 0, 0, seq, idx, more, part, base, to_inc, len(src), lc, lk, lt, lm, lj, na, 0
        )
        if na:
            if 0 in acks:
                raise MessageError("acks must be positive integers")
            tail = _u64s(na).pack(*acks)
            data = b"".join((orig.prefix, head, src, c, k, t, m, j, tail, _json(fields).encode() if fields else b""))
        else:
            data = b"".join((orig.prefix, head, src, c, k, t, m, j, _json(fields).encode() if fields else b""))
    except MessageError:
        raise
    except (TypeError, ValueError, RecursionError, KeyError, struct.error) as e:
        raise MessageError(f"{msg or 'msg'} in {conv or '-'} cannot be encoded: {e}") from None
    if len(data) > MAX_DATAGRAM:
        raise _oversize(msg or "msg", conv, len(data))
    return data


def _loads(text: str) -> Any:
    """json.loads(text), through the C scanner alone when the text is one compact value (ours always is)."""
    try:
        value, end = _scan(text, 0)
        if end == len(text):
            return value
    except StopIteration:
        pass
    return _json_loads(text)  # whitespace around the value, or an error worth json's own message


def decode(data: bytes) -> Envelope:
    """Parse one datagram; anything malformed raises MessageError saying what is wrong."""
    n = len(data)
    if n > MAX_DATAGRAM:
        raise MessageError(f"datagram of {n} bytes is over the limit {MAX_DATAGRAM}")
    if not data.startswith(HEADER):  # (this build's version: one test for the usual case)
        if data[:3] != MAGIC:
            raise MessageError("not a GWC datagram (bad magic)")
        if n < 4 or not MIN_VERSION <= data[3] <= VERSION:
            raise MessageError(
                f"unknown wire version {data[3] if n > 3 else None} (this build reads {MIN_VERSION}..{VERSION})"
            )
    names = _DECODED
    try:
        (
            inc,
            src_tag,
            to_tag,
            cls_tag,
            subj_tag,
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
            na,
            ni,
        ) = _FIXED.unpack_from(data, 4)
        if max(ls, lc, lk, lt, lm, lj) > MAX_NAME:
            raise MessageError(f"a name is longer than {MAX_NAME} bytes")
        o = _BODY + ls
        c = o + lc
        k = c + lk
        t = k + lt
        m = t + lm
        e = m + lj
        if e > n:
            raise MessageError("truncated datagram")
        if b"\0" in data[_BODY:e]:
            raise MessageError("a name holds a NUL byte")
        # Names through the cache (the empty name is in it, with tag 0); each tag must match its name.
        b = data[_BODY:o]
        src, t1 = names.get(b) or _decoded(b)
        conv = data[o:c].decode()
        b = data[c:k]
        cls, t2 = names.get(b) or _decoded(b)
        b = data[k:t]
        to, t3 = names.get(b) or _decoded(b)
        if t1 != src_tag or t2 != cls_tag or t3 != to_tag:
            raise MessageError("a filter tag does not match its name")
        b = data[t:m]
        msg = (names.get(b) or _decoded(b))[0]
        o = m
        subject = ""
        if lj or subj_tag:
            b = data[o:e]
            subject, t4 = names.get(b) or _decoded(b)
            if t4 != subj_tag:
                raise MessageError("a filter tag does not match its name")
        acks: tuple[int, ...] = ()
        if na:
            acks = _u64s(na).unpack_from(data, e)
            e += 8 * na
            if 0 in acks:
                raise MessageError("acks must be positive integers")
        interest: tuple[str, ...] = ()
        subjects: tuple[tuple[str, str], ...] = ()
        if ni:
            whole, narrow = [], []
            for _ in range(ni):
                o, e = e + 1, e + 1 + data[e]
                if e >= n:
                    raise MessageError("truncated datagram")
                if not 0 < e - o <= MAX_NAME or b"\0" in data[o:e]:
                    raise MessageError(f"an interest entry is empty, over {MAX_NAME} bytes or holds a NUL byte")
                cl = data[o:e].decode()
                o, e = e + 1, e + 1 + data[e]
                if e > n:
                    raise MessageError("truncated datagram")
                if b"\0" in data[o:e]:
                    raise MessageError("an interest entry's subject holds a NUL byte")
                if e > o:
                    narrow.append((cl, data[o:e].decode()))
                else:
                    whole.append(cl)
            interest, subjects = tuple(whole), tuple(narrow)
        fields = {}
        if e < n:
            fields = _loads(data[e:].decode())
            if type(fields) is not dict:
                raise MessageError("fields are not a JSON object")
    except MessageError:
        raise
    except (struct.error, IndexError):
        raise MessageError("truncated datagram") from None
    except (UnicodeDecodeError, ValueError, RecursionError) as err:  # ValueError covers JSONDecodeError, huge ints
        raise MessageError(f"undecodable datagram: {str(err)[:200]}") from None
    if kind > 3:  # len(KINDS) - 1
        raise MessageError(f"unknown kind {kind}")
    if flags & ~QUERY:
        raise MessageError(f"unknown flags {flags:#x}")
    if not src:
        raise MessageError("empty src")
    if kind == 0:
        if not (conv and cls and msg and seq > 0):
            raise MessageError("a msg needs conv, cls, msg and a positive seq")
        if part and more:
            raise MessageError("only the first message of a batch (part 0) says how many follow")
        if base > idx:
            raise MessageError("base is beyond idx")
    return Envelope(
        KINDS[kind],
        src,
        inc,
        seq,
        conv,
        cls,
        idx,
        more,
        part,
        base,
        to or None,
        msg,
        fields,
        acks,
        to_inc,
        interest,
        bool(flags),
        subject,
        subjects,
        data[3],
    )


# Classic BPF (Linux's SO_ATTACH_FILTER), as (code, jt, jf, k): what kernel_filter is made of.
_LD_W, _LD_B, _LD_LEN, _TAX, _SUB_X, _JEQ, _JGE, _RET = 0x20, 0x30, 0x80, 0x07, 0x1C, 0x15, 0x35, 0x06
UDP_HEADER = 8  # Linux runs a UDP socket's filter on the datagram from its UDP header: payload offsets + 8
_WHOLE = 0xFFFF_FFFF  # a filter's "keep the whole datagram"
MAX_FILTERED_SUBJECTS = 64  # more subjects than this, and the kernel keeps their classes whole (jumps are 8 bits)


def kernel_filter(
    src: str,
    inc: int,
    interest: Iterable[str],
    ignored: tuple[str, ...] = (),
    subjects: Mapping[str, Iterable[str]] | None = None,
) -> list[tuple[int, int, int, int]]:
    """The socket filter for module `src` (incarnation `inc`) listening to `interest`.

    It keeps exactly what the bus would not drop unread: every datagram that is too short or not of
    a version this build reads (so the bus logs it), hellos and byes for everyone, acks, msgs and hellos (answers
    to its query) addressed to `src`, and broadcast msgs of a class in `interest` or of a
    conversation's later batches (a conversation the module holds is received whatever its
    interest), or of a class in `subjects` about one of its subjects there. It drops the module's own
    datagrams, and the hellos and byes of the modules it does not track (names beginning with one of
    `ignored`: the bus would drop them unread); their acks to it are kept. Tags can
    collide, so it may keep a little more than needed, never less: the bus checks every datagram it
    reads again.
    """
    own, hi, lo = tag(src), inc >> 32, inc & 0xFFFF_FFFF
    u = UDP_HEADER
    whole = {tag(c) for c in interest}
    # A class heard about some subjects only: its tag, then theirs (a class heard whole needs no more).
    narrow: dict[int, set[int]] = {}
    for c, about in (subjects or {}).items():
        if tag(c) not in whole:
            narrow.setdefault(tag(c), set()).update(tag(a) for a in about)
    if sum(len(t) for t in narrow.values()) > MAX_FILTERED_SUBJECTS:  # jumps are 8 bits: kept whole, the bus sorts
        whole.update(narrow)
        narrow = {}
    about_prog: list[Any] = []
    for n, (_cls_tag, stags) in enumerate(sorted(narrow.items())):
        about_prog += [
            f"about_{n}",
            ((_LD_W, u + OFF_SUBJ_TAG), None, None),
            *(((_JEQ, t), "keep", None) for t in sorted(stags)),
            ((_JEQ, 0), "drop", "drop"),
        ]
    # (instruction, label to jump to when true, when false); None falls through.
    prog: list[tuple[tuple[int, int], str | None, str | None] | str] = [
        ((_LD_LEN, 0), None, None),
        ((_JGE, u + _BODY), None, "keep"),
        ((_LD_W, u), None, None),  # magic and version: a version this build does not read is kept (and logged)
        ((_JGE, int.from_bytes(MAGIC + bytes([MIN_VERSION]), "big")), None, "keep"),
        ((_JGE, int.from_bytes(MAGIC + bytes([VERSION + 1]), "big")), "keep", None),
        ((_LD_W, u + OFF_INC), None, None),
        ((_JEQ, hi), None, "not_own"),
        ((_LD_W, u + OFF_INC + 4), None, None),
        ((_JEQ, lo), None, "not_own"),
        ((_LD_W, u + OFF_SRC_TAG), None, None),
        ((_JEQ, own), "drop", None),
        "not_own",
        ((_LD_B, u + OFF_KIND), None, None),
        ((_JEQ, _KIND_CODE["msg"]), "msg", None),
        ((_JEQ, _KIND_CODE["ack"]), "ours", None),
        *_from(ignored, "drop", "ours"),
        "ours",
        # ack, hello, bye: addressed to us, or to nobody in particular (a hello or bye for everyone)
        ((_LD_W, u + OFF_TO_TAG), None, None),
        ((_JEQ, own), "keep", None),
        ((_JEQ, 0), "keep", "drop"),
        "msg",
        ((_LD_W, u + OFF_TO_TAG), None, None),
        ((_JEQ, own), "keep", None),
        ((_JEQ, 0), None, "drop"),
        ((_LD_W, u + OFF_PART), None, None),
        ((_TAX, 0), None, None),
        ((_LD_W, u + OFF_IDX), None, None),
        ((_SUB_X, 0), None, None),
        ((_JEQ, 0), None, "keep"),  # idx - part > 0: a later batch of a conversation begun before
        ((_LD_W, u + OFF_CLS_TAG), None, None),
        *(((_JEQ, t), "keep", None) for t in sorted(whole)),
        *(((_JEQ, t), f"about_{n}", None) for n, t in enumerate(sorted(narrow))),
        ((_JEQ, 0), "drop", "drop"),
        *about_prog,
        "drop",
        ((_RET, 0), None, None),
        "keep",
        ((_RET, _WHOLE), None, None),
    ]
    return _assemble(prog)


def beat_filter(ignored: tuple[str, ...]) -> list[tuple[int, int, int, int]]:
    """The beat socket's filter for a module that tracks no module whose name begins with one of `ignored`:
    their beats are dropped before the module wakes to read them. Like kernel_filter, it keeps
    anything too short to tell, and the bus checks what it reads again."""
    prog = [*_from(ignored, None, "keep"), ((_RET, 0), None, None), "keep", ((_RET, _WHOLE), None, None)]
    return _assemble(prog)


def _from(prefixes: tuple[str, ...], yes: str | None, no: str) -> list[Any]:
    """Instructions that go to `yes` when the sender's name begins with one of `prefixes` (None: fall
    through), else to `no`; a datagram too short to tell goes to `no`. No prefix: straight to `no`."""
    if not prefixes:
        return [((_JEQ, 0), no, no)]
    at = UDP_HEADER + _BODY  # where the sender's name begins
    matched = yes or "from_matched"
    prog: list[Any] = []
    for n, prefix in enumerate(prefixes):
        name = prefix.encode()
        other = f"from_{n + 1}" if n + 1 < len(prefixes) else no  # the next prefix, after the last `no`
        if n:
            prog.append(f"from_{n}")
        prog += [
            ((_LD_LEN, 0), None, None),
            ((_JGE, at + len(name)), None, other),
            ((_LD_B, UDP_HEADER + SRC_LEN_OFFSET), None, None),
            ((_JGE, len(name)), None, other),
        ]
        for i, byte in enumerate(name):
            prog += [((_LD_B, at + i), None, None), ((_JEQ, byte), matched if i == len(name) - 1 else None, other)]
    return prog if yes else [*prog, "from_matched"]


def _assemble(prog: list[Any]) -> list[tuple[int, int, int, int]]:
    """Classic BPF from (instruction, jump-if-true label, jump-if-false label) items and labels."""
    where: dict[str, int] = {}  # label -> index of the instruction after it
    n = 0
    for item in prog:
        if isinstance(item, str):
            where[item] = n
        else:
            n += 1
    code: list[tuple[int, int, int, int]] = []
    for item in prog:
        if isinstance(item, str):
            continue
        (op, k), yes, no = item
        here = len(code) + 1
        jt, jf = where[yes] - here if yes else 0, where[no] - here if no else 0
        if not (0 <= jt <= 255 and 0 <= jf <= 255):
            raise ValueError(f"socket filter jump of {max(jt, jf)} instructions: too far for classic BPF")
        code.append((op, jt, jf, k))
    return code
