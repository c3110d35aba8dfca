"""The cell's pending alarms as OPC UA conditions (Part 9), a part the gateway holds: each alarm an
AlarmConditionType event emitted by the Server object (where clients subscribe to events) and a node
under Alarms, its ConditionId. The cell raises and clears an alarm; a client may acknowledge and then
confirm it, which changes nothing in the cell (clearing is ClearAlarm's, an explicit act).
"""

from __future__ import annotations

import asyncio
import copy
import logging
import re
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from asyncua import ua
from asyncua.server.event_generator import EventGenerator

from gwc.ipc.codes import AckCode
from gwc.opcua import model
from gwc.opcua.answers import result
from gwc.opcua.space import ALARM, Space, check_arguments

V = ua.VariantType
S = ua.StatusCodes
SEVERITY = {"note": 200, "warning": 500, "error": 800}  # OPC UA event severity, 1..1000
# Part 9's methods of a condition, as asyncua's standard address space numbers them.
ACKNOWLEDGE = ua.ObjectIds.AcknowledgeableConditionType_Acknowledge
CONFIRM = ua.ObjectIds.AcknowledgeableConditionType_Confirm
CONDITION_ARGS = [("EventId", V.ByteString, "the event"), ("Comment", V.LocalizedText, "a comment")]


@dataclass
class Condition:
    """A pending alarm as an OPC UA condition (Part 9): the cell raises and clears it; a client may
    acknowledge and then confirm it, which changes nothing in the cell."""

    row: dict[str, Any]
    acked: bool = False
    confirmed: bool = False
    comment: str = ""
    event_ids: set[bytes] = field(default_factory=set)  # the events told of it: an Acknowledge names one


class AlarmConditions:
    """The pending alarms as raised to OPC UA clients, by alarm number; `refresh(rows)` brings them in
    line with the cell's, `cleared` ends one at once (ALARM_CLE heard)."""

    def __init__(
        self, space: Space, types: model.CellTypes, events: EventGenerator, machine_ids: list[str], log: logging.Logger
    ) -> None:
        self.space, self.types, self.machine_ids, self.log = space, types, machine_ids, log
        self.alarms: dict[int, Condition] = {}
        self._events = events
        self._template = copy.copy(events.event)
        self._template.add_property("ConfirmedState", None, V.LocalizedText)
        self._template.add_property("ConfirmedState/Id", None, V.Boolean)
        self._event_lock = asyncio.Lock()

    @classmethod
    async def serve(
        cls, server: Any, space: Space, types: model.CellTypes, machine_ids: list[str], log: logging.Logger
    ) -> AlarmConditions:
        """Conditions on `server`: its AlarmConditionType events, and Part 9's Acknowledge and Confirm
        linked to this object."""
        events = await server.get_event_generator(ua.ObjectIds.AlarmConditionType, ua.ObjectIds.Server)
        conditions = cls(space, types, events, machine_ids, log)
        server.link_method(server.get_node(ACKNOWLEDGE), conditions.acknowledge)
        server.link_method(server.get_node(CONFIRM), conditions.confirm)
        return conditions

    async def refresh(self, rows: list[dict[str, Any]]) -> None:
        """The cell's pending alarms, as read: those gone are cleared, the new ones raised."""
        pending = {int(r["alarm_no"]): r for r in rows}
        for no in [n for n in self.alarms if n not in pending]:
            await self.cleared(no, "cleared")
        for no, row in pending.items():
            if no not in self.alarms:
                await self.raised(row)

    async def raised(self, row: dict[str, Any]) -> None:
        sp, types = self.space, self.types
        no = int(row["alarm_no"])
        condition = self.alarms[no] = Condition(row)
        await sp.object(sp.nodeid("alarms"), f"alarms/{no}", f"alarm_{no}", ALARM, types.alarm, ua.ObjectIds.Organizes)
        await sp.set_all(f"alarms/{no}", row, ALARM, row["raised_at"])
        await self._event(condition, active=True, text=row["alarm_text"], at=row["raised_at"])
        self.log.info("alarm %d %s raised to OPC UA clients", no, row["alarm_id"])

    async def cleared(self, alarm_no: int, how: str) -> None:
        condition = self.alarms.pop(alarm_no, None)
        if condition is None:
            return
        row = condition.row
        # The cell's clearing is the operator's act on the alarm itself: acknowledged and confirmed.
        condition.acked = condition.confirmed = True
        await self._event(condition, active=False, text=f"{row['alarm_text']} ({how})", at=datetime.now(UTC))
        await self.space.remove(f"alarms/{alarm_no}")
        self.log.info("alarm %d %s %s: told OPC UA clients", alarm_no, row["alarm_id"], how)

    async def _event(self, condition: Condition, active: bool, text: str, at: datetime) -> None:
        """One AlarmConditionType event. Retained (ConditionRefresh sends it again) while the alarm is
        active, or not yet acknowledged or confirmed; a cleared alarm is inactive, acknowledged and
        confirmed (the cell clears it as one act) and no longer retained."""
        sp = self.space
        row = condition.row
        machine = row["machine_id"]
        ev = copy.copy(self._template)
        ev.SourceNode = sp.nodeid(f"machines/{machine}" if machine in self.machine_ids else "cell")
        ev.SourceName = machine or "cell"
        ev.NodeId = sp.nodeid(f"alarms/{row['alarm_no']}")
        ev.ConditionName = row["alarm_id"] or "unknown"
        ev.Severity = SEVERITY.get(row["severity"], 500)
        ev.Retain = active or not condition.acked or not condition.confirmed
        ev.Comment = ua.LocalizedText(condition.comment) if condition.comment else None
        for state, on, (yes, no) in (
            ("EnabledState", True, ("Enabled", "Disabled")),
            ("ActiveState", active, ("Active", "Inactive")),
            ("AckedState", condition.acked, ("Acknowledged", "Unacknowledged")),
            ("ConfirmedState", condition.confirmed, ("Confirmed", "Unconfirmed")),
        ):
            setattr(ev, state, ua.LocalizedText(yes if on else no))
            setattr(ev, f"{state}/Id", on)
        async with self._event_lock:  # the generator holds one event at a time
            self._events.event = ev
            await self._events.trigger(at, text)
            condition.event_ids.add(ev.EventId.Value)

    def _condition(self, object_id: ua.NodeId, given: tuple[ua.Variant, ...]) -> tuple[Condition | None, Any]:
        """The condition an Acknowledge or Confirm names, or the refusal (a CallMethodResult)."""
        refused = check_arguments(given, CONDITION_ARGS)
        if refused is not None:
            return None, refused
        path = self.space.path_of(object_id)
        m = re.fullmatch(r"alarms/(\d+)", path or "")
        condition = self.alarms.get(int(m.group(1))) if m else None
        if condition is None:
            return None, result(S.BadNodeIdUnknown, f"{object_id.to_string()} is not a pending alarm of the cell")
        if given[0].Value not in condition.event_ids:
            return None, result(S.BadEventIdUnknown, "no event of this condition has that EventId")
        return condition, None

    async def acknowledge(self, object_id: ua.NodeId, *given: ua.Variant) -> ua.CallMethodResult:
        """Part 9 Acknowledge: the condition is acknowledged, nothing else. The cell's alarm stays
        pending (clearing HOME_CMM would start the CMM: that is ClearAlarm's, an explicit act)."""
        condition, refused = self._condition(object_id, given)
        if condition is None:
            self.log.warning("OPC UA Acknowledge of %s refused: %s", object_id.to_string(), refused.StatusCode.name)
            out: ua.CallMethodResult = refused
            return out
        if condition.acked:
            return result(S.BadConditionBranchAlreadyAcked, "the alarm is acknowledged already")
        condition.acked = True
        condition.comment = given[1].Value.Text or ""
        no = condition.row["alarm_no"]
        self.log.info(
            "alarm %s %s acknowledged by an OPC UA client: %s", no, condition.row["alarm_id"], condition.comment
        )
        await self._event(condition, True, f"{condition.row['alarm_text']} (acknowledged)", datetime.now(UTC))
        return result(AckCode.ACK_OK, f"alarm {no} acknowledged; it stays pending until cleared (ClearAlarm)")

    async def confirm(self, object_id: ua.NodeId, *given: ua.Variant) -> ua.CallMethodResult:
        """Part 9 Confirm: after an Acknowledge, the operator confirms the alarm was seen to."""
        condition, refused = self._condition(object_id, given)
        if condition is None:
            out: ua.CallMethodResult = refused
            return out
        if not condition.acked:
            return result(S.BadConditionBranchAlreadyConfirmed, "acknowledge the alarm before confirming it")
        if condition.confirmed:
            return result(S.BadConditionBranchAlreadyConfirmed, "the alarm is confirmed already")
        condition.confirmed = True
        condition.comment = given[1].Value.Text or ""
        await self._event(condition, True, f"{condition.row['alarm_text']} (confirmed)", datetime.now(UTC))
        return result(AckCode.ACK_OK, f"alarm {condition.row['alarm_no']} confirmed")
