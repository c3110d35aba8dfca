"""What the web does to the cell: the conversations the `gwc` commands hold, held on the web module's
own bus attachment (as the OPC UA gateway holds them), each in the name of the person who asked
(`by` = `web:NAME`). A refusal of the owning module is raised (Refused, with its ack code)."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from gwc.cell import hi_bus
from gwc.config import Config
from gwc.errors import GwcError, ModuleError, Refused
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import ask, module_name

ANSWER = 5.0  # s a server has to answer
COMPLETE_WAIT = 3.0  # s a start or stop is waited for before "accepted, not finished" (the status tells the end)
DECISIONS = {
    "import": Conv.IMPORT_LOT,
    "export": Conv.EXPORT_LOT,
    "retry": Conv.RELEASE_LOT,
    "reroute": Conv.RELEASE_LOT,
    "fail": Conv.RELEASE_LOT,
}


class Actions:
    def __init__(self, cfg: Config, bus: Bus, log: logging.Logger) -> None:
        self.cfg = cfg
        self.bus = bus
        self.log = log
        self._order_lock = asyncio.Lock()  # one HI bus attachment (hi.<pid>) at a time

    async def machine(self, machine: str, start: bool) -> str:
        """ME_START or ME_SHUT with the machine's WC, as `gwc machine start|stop` holds it."""
        self.cfg.machine(machine)  # ConfigError naming the machines
        wc = module_name("wc", machine)
        if wc not in self.bus.peers():
            raise ModuleError(
                f"{wc} is not on the bus: its processes are down (gwc machine start {machine} on its host)"
            )
        cls, opener = (Conv.ME_START, Msg.STARTUP_REQUEST) if start else (Conv.ME_SHUT, Msg.SHUTDOWN_REQUEST)
        done = (Msg.STARTUP_COMPLETE, Msg.ME_READY) if start else (Msg.SHUTDOWN_COMPLETE, Msg.ME_STOPPED)
        conv, batch = await self.bus.request(cls, message(opener, module=wc), to=wc, timeout=ANSWER)
        try:
            ack = batch.first
            if ack.ack_code == AckCode.NOTNOW:
                return ack.note or ("already started" if start else "already stopped")
            if ack.ack_code != AckCode.ACK_OK:
                raise Refused(ack.ack_code, ack.note or "")
            try:
                async with asyncio.timeout(COMPLETE_WAIT):
                    while (end := (await conv.next_message()).first).name not in done:
                        pass
            except TimeoutError:
                return f"{wc} accepted {cls}; not finished yet (its status will tell)"
            if end.ack_code not in (AckCode.ACK_OK, None):
                raise Refused(end.ack_code, end.fields.get("note") or "")
            return "started" if start else "stopped"
        finally:
            conv.end()

    async def clear_alarm(self, alarm_no: int, by: str) -> str:
        first = message(Msg.ALARM_CLEAR_REQUEST, alarm_no=alarm_no, cleared_by=by)
        ack = await ask(self.bus, Conv.ALARM_CLR_REQ, first, "cas", ANSWER)
        if ack.ack_code != AckCode.ACK_OK:
            raise Refused(ack.ack_code, ack.note or "")
        return f"alarm {alarm_no} cleared"

    async def decide(self, entity_id: int, decision: str, by: str) -> str:
        """Import, export, or release a held entity (retry, reroute, fail)."""
        cls = DECISIONS.get(decision)
        if cls is None:
            raise GwcError(f"no decision {decision!r} (one of {', '.join(DECISIONS)})")
        first = message(Msg.LOT_DECISION, entity_id=entity_id, action=decision, by=by)
        ack = await ask(self.bus, cls, first, "ls", ANSWER)
        if ack.ack_code == AckCode.UNKNOWN:
            raise GwcError(f"unknown lot entity {entity_id}")
        if ack.ack_code != AckCode.ACK_OK:
            raise Refused(ack.ack_code, ack.note or f"cannot {decision} entity {entity_id}")
        return f"entity {entity_id}: {decision} done"

    async def enter_order(self, customer: str, items: list[tuple[str, int]], priority: int | None) -> dict[str, Any]:
        """Work Order Entry by the HI's own code (it writes WORK_ORDERS as gwc_hi, asks the Lot Server
        for the lots and starts their scripts), in a thread: it is blocking."""
        from gwc.client.orders import enter_order

        def run() -> dict[str, Any]:
            with hi_bus(self.cfg, self.log) as bus:
                return enter_order(self.cfg, self.log, bus, customer, items, priority=priority)

        async with self._order_lock:
            return await asyncio.to_thread(run)

    async def downtime_reason(self, event_id: int, reason: str, by: str) -> str:
        """DOWNTIME_RSN to the Machine Server, as `gwc downtime reason` asks it (a reason of the tree)."""
        if reason not in self.cfg.record.reasons:
            known = "; ".join(f"{c}: {', '.join(rs)}" for c, rs in self.cfg.record.tree().items())
            raise GwcError(f"{reason!r} is not in the reason tree ({known})")
        first = message(Msg.DOWNTIME_REASON, event_id=event_id, machine_id=None, reason=reason, by=by)
        ack = await ask(self.bus, Conv.DOWNTIME_RSN, first, "ms", ANSWER)
        if ack.ack_code == AckCode.UNKNOWN:
            raise GwcError(ack.note or f"no downtime event {event_id}")
        if ack.ack_code != AckCode.ACK_OK:
            raise Refused(ack.ack_code, ack.note or "the Machine Server did not take the reason")
        return f"downtime {event_id}: {reason} ({ack.fields.get('e10_state') or ''})"

    async def approve_recipe(self, recipe_id: str, version: int | None, by: str) -> str:
        """RECIPE_APPR to the Equipment Recipe Server, as `gwc recipe approve` asks it (default: the
        latest version)."""
        first = message(Msg.RECIPE_APPROVE, recipe_id=recipe_id, version=version, by=by)
        ack = await ask(self.bus, Conv.RECIPE_APPR, first, "ers", ANSWER)
        if ack.ack_code != AckCode.ACK_OK:
            raise Refused(ack.ack_code, ack.note or f"the recipe server did not approve {recipe_id}")
        checksum = str(ack.fields.get("checksum") or "")[:12]
        return f"{recipe_id} v{ack.fields.get('version')} approved (sha256 {checksum})"
