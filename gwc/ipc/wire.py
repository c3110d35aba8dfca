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

KINDS = ("msg", "ack", "hello", "bye")


@dataclass(frozen=True)
class Envelope:
    """Everything one datagram carries. Which fields matter depends on kind (see docs/protocol.md)."""

    kind: str
    src: str  # sender's module name on the bus, e.g. "msched", "wc:cmm_wc", "lot:17"
    inc: int  # sender's incarnation: random per process start, so a restart is a new sender
    seq: int = 0  # msg: per-(src, inc) datagram number, echoed by acks
    conv: str = ""  # msg: conversation id, "<initiator>.<inc hex>.<n>"
    cls: str = ""  # msg: conversation class, e.g. "MACH_REQ"
    idx: int = 0  # msg: index of this message among those src sent in conv
    more: int = 0  # msg: how many messages of the same batch follow this one
    to: str | None = None  # msg/ack: addressee module name; None = everyone interested in cls
    msg: str = ""  # msg: message class, e.g. "Machine_Request"
    fields: dict[str, Any] = field(default_factory=dict)
    acks: tuple[int, ...] = ()  # ack: the seqs acknowledged
    to_inc: int = 0  # ack: the incarnation of the addressee
    interest: tuple[str, ...] = ()  # hello: classes src listens to now
    query: bool = False  # hello: "tell me who you are" (peers answer with their own hello)


_KEYS = {
    "k": ("kind", str),
    "s": ("src", str),
    "n": ("inc", int),
    "q": ("seq", int),
    "c": ("conv", str),
    "C": ("cls", str),
    "i": ("idx", int),
    "+": ("more", int),
    "t": ("to", (str, type(None))),
    "m": ("msg", str),
    "f": ("fields", dict),
    "a": ("acks", list),
    "T": ("to_inc", int),
    "I": ("interest", list),
    "?": ("query", bool),
}
_SHORT = {attr: key for key, (attr, _) in _KEYS.items()}
_DEFAULTS = Envelope(kind="msg", src="", inc=0)


def encode(env: Envelope) -> bytes:
    """Serialise, leaving out fields at their defaults; refuse what cannot fit one datagram."""
    body: dict[str, Any] = {"k": env.kind, "s": env.src, "n": env.inc}
    for attr, key in _SHORT.items():
        if attr in ("kind", "src", "inc"):
            continue
        value = getattr(env, attr)
        if value != getattr(_DEFAULTS, attr):
            body[key] = list(value) if isinstance(value, tuple) else value
    data = HEADER + json.dumps(body, separators=(",", ":"), ensure_ascii=False).encode()
    if len(data) > MAX_DATAGRAM:
        raise MessageError(
            f"{env.msg or env.kind} in {env.conv or '-'} is {len(data)} bytes, over the bus limit of "
            f"{MAX_DATAGRAM}: send large payloads (recipes, results) through the database, not the bus"
        )
    return data


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
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise MessageError(f"undecodable body: {e}") from None
    if not isinstance(body, dict):
        raise MessageError("body is not a JSON object")
    kwargs: dict[str, Any] = {}
    for key, value in body.items():
        spec = _KEYS.get(key)
        if spec is None:
            raise MessageError(f"unknown key {key!r}")
        attr, typ = spec
        if not isinstance(value, typ) or (typ is int and isinstance(value, bool)):
            raise MessageError(f"key {key!r} ({attr}) has the wrong type {type(value).__name__}")
        kwargs[attr] = value
    for required in ("kind", "src", "inc"):
        if required not in kwargs:
            raise MessageError(f"missing key for {required}")
    if kwargs["kind"] not in KINDS:
        raise MessageError(f"unknown kind {kwargs['kind']!r}")
    if "acks" in kwargs:
        if not all(isinstance(a, int) and not isinstance(a, bool) for a in kwargs["acks"]):
            raise MessageError("acks must be integers")
        kwargs["acks"] = tuple(kwargs["acks"])
    if "interest" in kwargs:
        if not all(isinstance(c, str) for c in kwargs["interest"]):
            raise MessageError("interest must be strings")
        kwargs["interest"] = tuple(kwargs["interest"])
    env = Envelope(**kwargs)
    if env.kind == "msg" and not (env.conv and env.cls and env.msg and env.seq > 0):
        raise MessageError("a msg needs conv, cls, msg and a positive seq")
    if env.idx < 0 or env.more < 0 or env.seq < 0:
        raise MessageError("idx, more and seq must not be negative")
    return env
