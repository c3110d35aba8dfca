"""The gateway's methods that hold a conversation with the cell (docs/opcua.md, Methods): a machine's
Start and Stop (ME_START / ME_SHUT with its WC, as `gwc machine start|stop` holds them), ClearAlarm,
ImportLot and ExportLot, CancelRequest, and Work Order Entry by the HI's own client code. Each answers
with the cell's ack code as an OPC UA status. A part the gateway holds; the methods the `gwc` command's
client code does (Unreserve, MaintenanceDone) are HiMethods', which shares `converse` and `lock`.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import ua

from gwc.cell import hi_bus
from gwc.config import Config
from gwc.errors import ConversationTimeout, GwcError
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import ask, module_name
from gwc.opcua.answers import result
from gwc.opcua.door import OpcuaDoor

V = ua.VariantType
S = ua.StatusCodes
# asyncua serves one client connection's requests one after the other, and asyncua's client gives up
# a connection whose server does not answer its probe within 1 s: a method must not hold its client
# longer than this for a machine to finish starting or stopping (a CMM waits to be homed).
COMPLETE_WAIT = 0.5
PRIORITIES = (1, 1000)  # a work order's priority (0: the cell's default, 20)


class CellMethods:
    """The gateway's conversations with the cell, one per OPC UA method; `by` is who acted, as the cell
    records it; `lock` keeps the gateway to one HI bus attachment (hi.<pid>) at a time."""

    def __init__(self, cfg: Config, log: logging.Logger, bus: Bus, method_timeout: float, door: OpcuaDoor) -> None:
        self.cfg, self.log, self.bus, self.door = cfg, log, bus, door
        self.method_timeout = method_timeout
        self.by = f"opcua:{cfg.cell_name}"
        self.lock = asyncio.Lock()

    async def converse(self, what: str, call: Callable[[], Awaitable[ua.CallMethodResult]]) -> ua.CallMethodResult:
        """Run one method's conversation; a silent module or a refusal becomes a status, logged."""
        try:
            out = await call()
        except ConversationTimeout as e:
            out = result(AckCode.TIMEOUT, str(e))
        except GwcError as e:
            out = result(AckCode.BAD_MESSAGE, str(e))
        await self.door.done(out)
        code = out.OutputArguments[0].Value if out.OutputArguments else out.StatusCode.name
        self.log.info(
            "OPC UA method %s: %s %s", what, code, out.OutputArguments[1].Value if out.OutputArguments else ""
        )
        return out

    async def ask(self, cls: str, first: Message, to: str) -> ua.CallMethodResult:
        answer = await ask(self.bus, cls, first, to, timeout=self.method_timeout)
        return result(answer.ack_code, answer.fields.get("note") or "")

    async def _machine_conversation(
        self, machine: str, cls: str, opener: str, done: tuple[str, ...]
    ) -> ua.CallMethodResult:
        """ME_START / ME_SHUT with a machine's WC, as `gwc machine start|stop` holds it. A machine that
        takes longer than COMPLETE_WAIT (a CMM waiting to be homed, a run to finish first) answers
        GoodCompletesAsynchronously: the change will show in its status."""
        wc = module_name("wc", machine)
        if wc not in self.bus.peers():
            return result(AckCode.NOTNOW, f"{wc} is not on the bus: start its processes (gwc machine start {machine})")
        conv, batch = await self.bus.request(cls, message(opener, module=wc), to=wc, timeout=self.method_timeout)
        try:
            ack = batch.first
            if ack.ack_code == AckCode.NOTNOW:
                return result(AckCode.ACK_OK, ack.note or "nothing to do")
            if ack.ack_code != AckCode.ACK_OK:
                return result(ack.ack_code, ack.note or "")
            try:
                async with asyncio.timeout(COMPLETE_WAIT):  # not a failure: the status will tell the end
                    while (end := (await conv.next_message()).first).name not in done:
                        pass
            except TimeoutError:
                return result(S.GoodCompletesAsynchronously, f"{wc} accepted {cls}; not finished yet")
            return result(end.ack_code, end.fields.get("note") or "")
        finally:
            conv.end()

    async def start_machine(self, machine: str) -> ua.CallMethodResult:
        return await self.converse(
            f"Start {machine}",
            lambda: self._machine_conversation(
                machine, Conv.ME_START, Msg.STARTUP_REQUEST, (Msg.STARTUP_COMPLETE, Msg.ME_READY)
            ),
        )

    async def stop_machine(self, machine: str) -> ua.CallMethodResult:
        return await self.converse(
            f"Stop {machine}",
            lambda: self._machine_conversation(
                machine, Conv.ME_SHUT, Msg.SHUTDOWN_REQUEST, (Msg.SHUTDOWN_COMPLETE, Msg.ME_STOPPED)
            ),
        )

    async def clear_alarm(self, alarm_no: int) -> ua.CallMethodResult:
        """The operator's explicit clearing of an alarm (`gwc alarm clear`): for HOME_CMM it homes and
        starts the CMM. Never done by an Acknowledge."""
        if alarm_no < 1:
            return result(S.BadInvalidArgument, f"alarm_no {alarm_no}: alarm numbers are 1 or more")
        return await self.converse(
            f"ClearAlarm({alarm_no})",
            lambda: self.ask(
                Conv.ALARM_CLR_REQ,
                message(Msg.ALARM_CLEAR_REQUEST, alarm_no=alarm_no, cleared_by=self.by),
                "cas",
            ),
        )

    async def _decide(self, action: str, entity_id: int) -> ua.CallMethodResult:
        if entity_id < 1:
            return result(S.BadInvalidArgument, f"entity_id {entity_id}: entities are 1 or more")
        cls = Conv.IMPORT_LOT if action == "import" else Conv.EXPORT_LOT
        first = message(Msg.LOT_DECISION, entity_id=entity_id, action=action, by=self.by)
        return await self.converse(f"{action} entity {entity_id}", lambda: self.ask(cls, first, "ls"))

    async def import_lot(self, entity_id: int) -> ua.CallMethodResult:
        return await self._decide("import", entity_id)

    async def export_lot(self, entity_id: int) -> ua.CallMethodResult:
        return await self._decide("export", entity_id)

    async def cancel_request(self, request_key: int) -> ua.CallMethodResult:
        if request_key < 1:
            return result(S.BadInvalidArgument, f"request_key {request_key}: request keys are 1 or more")
        first = message(Msg.CANCEL_REQUEST, request_key=request_key, by=self.by)
        return await self.converse(f"CancelRequest({request_key})", lambda: self.ask(Conv.CANCEL_RE, first, "msched"))

    async def enter_work_order(self, customer: str | None, items: str | None, priority: int) -> ua.CallMethodResult:
        """Work Order Entry by the HI's own code (it writes WORK_ORDERS as the HI, the table's owner,
        asks the Lot Server for the lots and starts their lot scripts), in a thread: it is blocking.
        Everything that can be checked is checked before anything is written."""
        from gwc.client.orders import enter_order, parse_items

        if not (customer or "").strip():
            return result(S.BadInvalidArgument, "customer: a customer id is needed (gwc customer list)")
        if priority != 0 and not PRIORITIES[0] <= priority <= PRIORITIES[1]:
            return result(
                S.BadInvalidArgument, f"priority {priority}: 0 (the default) or {PRIORITIES[0]}..{PRIORITIES[1]}"
            )
        try:
            parsed = parse_items(tuple(i for i in re.split(r"[\s,]+", (items or "").strip()) if i))
        except GwcError as e:
            return result(S.BadInvalidArgument, str(e))
        cust = str(customer).strip()

        async def enter() -> ua.CallMethodResult:
            def run() -> dict[str, Any]:
                with hi_bus(self.cfg, self.log) as bus:
                    return enter_order(self.cfg, self.log, bus, cust, parsed, priority=priority or None)

            async with self.lock:  # one HI bus attachment (hi.<pid>) at a time
                made = await asyncio.to_thread(run)
            note = "; ".join(
                f"lot {lot['lot_id']}: {lot['quantity']} x {lot['product_id']} (entities "
                + ", ".join(map(str, lot["entities"]))
                + ")"
                for lot in made["lots"]
            )
            return result(AckCode.ACK_OK, note, ua.Variant(made["work_order_id"], V.Int64))

        return await self.converse(f"EnterWorkOrder({cust}, {items})", enter)
