"""Inter-process communication: the CELL bus (multicast conversations) and the WC<->ME queues.

The public names are assembled here: `from gwc.ipc import Bus, BlockingBus, Conversation, ...`. They
are loaded on first use (PEP 562), not when the package is: a process that only needs the wire
format, the catalogue or the queues (an ME, the configuration's keys) does not pay for the bus.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gwc.ipc.blocking import BlockingBus, BlockingConversation
    from gwc.ipc.bus import Bus
    from gwc.ipc.catalogue import Message
    from gwc.ipc.codes import AckCode
    from gwc.ipc.conversation import Batch, Conversation, Peer
    from gwc.ipc.names import Conv
    from gwc.ipc.outbox import Outbox

_WHERE = {
    "AckCode": "gwc.ipc.codes",
    "Batch": "gwc.ipc.conversation",
    "BlockingBus": "gwc.ipc.blocking",
    "BlockingConversation": "gwc.ipc.blocking",
    "Bus": "gwc.ipc.bus",
    "Conv": "gwc.ipc.names",
    "Conversation": "gwc.ipc.conversation",
    "Message": "gwc.ipc.catalogue",
    "Outbox": "gwc.ipc.outbox",
    "Peer": "gwc.ipc.conversation",
}

__all__ = [
    "AckCode",
    "Batch",
    "BlockingBus",
    "BlockingConversation",
    "Bus",
    "Conv",
    "Conversation",
    "Message",
    "Outbox",
    "Peer",
]


def __getattr__(name: str) -> Any:
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'gwc.ipc' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value  # the next lookup is a plain one
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])
