"""The bus wire format: one UDP datagram = 4-byte header + one compact JSON object.

Kept apart from the bus (as python-can keeps encoding apart from its transports) so that the
monitor, the fuzz tests and a client in another language share one definition. docs/protocol.md
is the normative description; this module is its reference implementation.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from gwc.errors import MessageError

MAGIC = b"GWC"
VERSION = 1
HEADER = MAGIC + bytes([VERSION])
MAX_DATAGRAM = 60_000  # below the 65,507-byte UDP limit, with room for IP options
MAX_NAME = 200  # module names, conversation ids and class names are short; longer is hostile

KINDS = ("msg", "ack", "hello", "bye")


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


_KEYS: dict[str, tuple[str, tuple[type, ...]]] = {
    "s": ("src", (str,)),
    "n": ("inc", (int,)),
    "k": ("kind", (str,)),
    "q": ("seq", (int,)),
    "c": ("conv", (str,)),
    "C": ("cls", (str,)),
    "i": ("idx", (int,)),
    "+": ("more", (int,)),
    "p": ("part", (int,)),
    "b": ("base", (int,)),
    "t": ("to", (str, type(None))),
    "m": ("msg", (str,)),
    "f": ("fields", (dict,)),
    "a": ("acks", (list,)),
    "T": ("to_inc", (int,)),
    "I": ("interest", (list,)),
    "?": ("query", (bool,)),
}
_ATTR = {key: attr for key, (attr, _) in _KEYS.items()}
# JSON yields exact types, so `type(v) in allowed` is the whole check (and keeps bool out of int).
_ALLOWED = {key: frozenset(types) for key, (_, types) in _KEYS.items()}
_INTS = frozenset(key for key, (_, types) in _KEYS.items() if types == (int,))
_STRS = frozenset(key for key, (attr, types) in _KEYS.items() if str in types and attr != "kind")
_dumps = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode


def encode(env: Envelope) -> bytes:
    """Serialise, leaving out fields at their defaults; refuse what cannot fit one datagram.

    src and inc come first, so a module can recognise its own looped-back datagrams by their prefix.
    """
    body: dict[str, Any] = {"s": env.src, "n": env.inc, "k": env.kind}
    if env.kind == "msg":
        body.update(q=env.seq, c=env.conv, C=env.cls, i=env.idx, m=env.msg)
        if env.more:
            body["+"] = env.more
        if env.part:
            body["p"] = env.part
        if env.base:
            body["b"] = env.base
        if env.fields:
            body["f"] = env.fields
    if env.to is not None:
        body["t"] = env.to
    if env.acks:
        body["a"] = list(env.acks)
        body["T"] = env.to_inc
    elif env.to_inc:
        body["T"] = env.to_inc
    if env.interest:
        body["I"] = list(env.interest)
    if env.query:
        body["?"] = True
    if env.kind != "msg":
        for key, value in (("q", env.seq), ("c", env.conv), ("C", env.cls), ("i", env.idx), ("m", env.msg),
                           ("+", env.more), ("p", env.part), ("b", env.base)):
            if value:
                body[key] = value
        if env.fields:
            body["f"] = env.fields
    try:
        data = HEADER + _dumps(body).encode()
    except (TypeError, ValueError) as e:
        raise MessageError(f"{env.msg or env.kind} in {env.conv or '-'} cannot be encoded: {e}") from None
    if len(data) > MAX_DATAGRAM:
        raise MessageError(
            f"{env.msg or env.kind} in {env.conv or '-'} is {len(data)} bytes, over the bus limit of "
            f"{MAX_DATAGRAM}: send large payloads (recipes, results) through the database, not the bus"
        )
    return data


def own_prefix(src: str, inc: int) -> bytes:
    """How every datagram this module encodes begins: lets it skip its own looped-back traffic cheaply."""
    return HEADER + (_dumps({"s": src, "n": inc})[:-1] + ",").encode()


def decode(data: bytes) -> Envelope:
    """Parse one datagram; anything malformed raises MessageError saying what is wrong."""
    if len(data) > MAX_DATAGRAM:
        raise MessageError(f"datagram of {len(data)} bytes is over the limit {MAX_DATAGRAM}")
    if data[:3] != MAGIC:
        raise MessageError("not a GWC datagram (bad magic)")
    if len(data) < 4 or data[3] != VERSION:
        raise MessageError(f"unknown wire version {data[3] if len(data) > 3 else None}")
    try:
        body = json.loads(data[4:].decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as e:  # ValueError covers JSONDecodeError, huge ints
        raise MessageError(f"undecodable body: {str(e)[:200]}") from None
    if not isinstance(body, dict):
        raise MessageError("body is not a JSON object")
    try:
        kwargs = {_ATTR[key]: value for key, value in body.items()}
    except KeyError as e:
        raise MessageError(f"unknown key {str(e.args[0])[:20]!r}") from None
    for key, value in body.items():
        if type(value) not in _ALLOWED[key]:
            raise MessageError(f"key {key!r} ({_ATTR[key]}) has the wrong type {type(value).__name__}")
        if key in _INTS:
            if not 0 <= value < 2**63:
                raise MessageError(f"key {key!r} ({_ATTR[key]}) is out of range")
        elif key in _STRS and len(value) > MAX_NAME:
            raise MessageError(f"key {key!r} ({_ATTR[key]}) is longer than {MAX_NAME} characters")
    for required in ("kind", "src", "inc"):
        if required not in kwargs:
            raise MessageError(f"missing key for {required}")
    if kwargs["kind"] not in KINDS:
        raise MessageError(f"unknown kind {str(kwargs['kind'])[:20]!r}")
    if not kwargs["src"]:
        raise MessageError("empty src")
    if "acks" in kwargs:
        if not all(isinstance(a, int) and not isinstance(a, bool) and a > 0 for a in kwargs["acks"]):
            raise MessageError("acks must be positive integers")
        kwargs["acks"] = tuple(kwargs["acks"])
    if "interest" in kwargs:
        if not all(isinstance(c, str) and len(c) <= MAX_NAME for c in kwargs["interest"]):
            raise MessageError("interest must be class names")
        kwargs["interest"] = tuple(kwargs["interest"])
    env = Envelope(**kwargs)
    if env.kind == "msg":
        if not (env.conv and env.cls and env.msg and env.seq > 0):
            raise MessageError("a msg needs conv, cls, msg and a positive seq")
        if env.part and env.more:
            raise MessageError("only the first message of a batch (part 0) says how many follow")
        if env.base > env.idx:
            raise MessageError("base is beyond idx")
    return env
