"""The Lot Server's divide, merge and destroy (thesis 1.4.4: "the creation of entities, division of
entities, merger of entities, and the destruction of entities"), for the HI and any tool: DIV_MERGE
and ENTITY_REQ destroy, asked of the Lot Server, the one writer of the lots' tables. The rules are
the Lot Server's (docs/servers.md, *Lot Server*)."""

from __future__ import annotations

from gwc.client.session import ANSWER, ask
from gwc.errors import GwcError, Refused
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg

__all__ = ["destroy_entity", "divide_entity", "merge_entities"]


def _checked(ack: Message, what: str) -> Message:
    if ack.ack_code == AckCode.UNKNOWN:
        raise GwcError(f"{what}: {ack.note or 'unknown entity'} (see `gwc lots`)")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, f"{what}: {ack.note or ack.ack_code}")
    return ack


def divide_entity(bus: BlockingBus, entity_id: int, quantity: int = 1, timeout: float = ANSWER) -> list[int]:
    """Divide: `quantity` new entities split off one that is created or imported, in its lot and state,
    each its child. Returns the new entities (without the one divided)."""
    msg = message(Msg.DIVIDE_MERGE, entity_id=entity_id, action="divide", quantity=quantity)
    ack = _checked(ask(bus, Conv.DIV_MERGE, msg, "ls", timeout), f"divide entity {entity_id}")
    return [int(e) for e in ack.entity_ids or [] if int(e) != entity_id]


def merge_entities(bus: BlockingBus, entity_id: int, other_id: int, timeout: float = ANSWER) -> None:
    """Merge: `other_id` folded into `entity_id` (the other is destroyed); both created or imported, of
    one lot and one state."""
    msg = message(Msg.DIVIDE_MERGE, entity_id=entity_id, action="merge", other_entity_id=other_id)
    _checked(ask(bus, Conv.DIV_MERGE, msg, "ls", timeout), f"merge entity {other_id} into {entity_id}")


def destroy_entity(bus: BlockingBus, entity_id: int, timeout: float = ANSWER) -> None:
    """Destroy: an entity that is created (not started), exported or failed leaves the lists; its rows
    stay, marked destroyed (the history keeps it)."""
    msg = message(Msg.ENTITY_REQUEST, entity_id=entity_id, action="destroy")
    _checked(ask(bus, Conv.ENTITY_REQ, msg, "ls", timeout), f"destroy entity {entity_id}")
