"""The production record's conversations: a downtime's reason to the Machine Server (DOWNTIME_RSN),
an operator's action on an entity to the Lot Server (LOT_ACTION); and the window `--since/--until`."""

from __future__ import annotations

import re
from datetime import datetime, timedelta
from zoneinfo import ZoneInfo

from gwc.client.session import ANSWER, ask
from gwc.errors import GwcError, Refused
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg

_AGO = re.compile(r"^-?(\d+(?:\.\d+)?)\s*([smhd])$")
_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def parse_when(text: str, timezone: str = "UTC", now: datetime | None = None) -> datetime:
    """A moment for --since/--until: `now`, `today` (its midnight), an age (`90s`, `20m`, `8h`, `2d`:
    that long ago) or an ISO 8601 time (without an offset: in the cell's [record] timezone)."""
    tz = ZoneInfo(timezone)
    now = now or datetime.now(tz)
    t = text.strip().lower()
    if t == "now":
        return now
    if t == "today":
        local = now.astimezone(tz)
        return datetime(local.year, local.month, local.day, tzinfo=tz)
    m = _AGO.match(t)
    if m:
        return now - timedelta(seconds=float(m.group(1)) * _UNITS[m.group(2)])
    try:
        when = datetime.fromisoformat(text.strip())
    except ValueError:
        raise GwcError(
            f"{text!r} is not a time: give now, today, an age (90s, 20m, 8h, 2d) or ISO 8601 (2026-11-28T10:00)"
        ) from None
    return when if when.tzinfo else when.replace(tzinfo=tz)


def set_downtime_reason(
    bus: BlockingBus, reason: str, by: str, event_id: int | None = None, machine_id: str | None = None
) -> Message:
    """DOWNTIME_RSN: the reason of downtime event `event_id` (or of `machine_id`'s open one)."""
    ack = ask(
        bus,
        Conv.DOWNTIME_RSN,
        message(Msg.DOWNTIME_REASON, event_id=event_id, machine_id=machine_id, reason=reason, by=by),
        "ms",
        ANSWER,
    )
    if ack.ack_code == AckCode.UNKNOWN:
        raise GwcError(ack.note or "no such downtime event (see `gwc downtime list`)")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or "the Machine Server did not take the reason")
    return ack


def record_action(bus: BlockingBus, entity_id: int, action: str, by: str, note: str | None = None) -> Message:
    """LOT_ACTION: an operator's action on an entity, kept in its history by the Lot Server."""
    ack = ask(bus, Conv.LOT_ACTION, message(Msg.LOT_ACTION, entity_id=entity_id, action=action, by=by, note=note), "ls")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"the Lot Server did not record {action} of entity {entity_id}")
    return ack
