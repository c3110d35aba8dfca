"""The gateway's methods done by the very client code the `gwc` command runs (gwc/client/): a
machine's Unreserve (6.2.4.7, `gwc unreserve`) and MaintenanceDone (1.4.2, `gwc machine
maintenance-done`). That code is blocking: it runs in a thread, on an HI bus attachment of the
gateway's own (hi.<pid>), one at a time (`lock`, which Work Order Entry shares)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable

from asyncua import ua

from gwc.cell import hi_bus
from gwc.client.machines import maintenance_done
from gwc.client.requests import unreserve_machine
from gwc.config import Config
from gwc.errors import ConversationTimeout, GwcError, Refused
from gwc.ipc.blocking import BlockingBus
from gwc.ipc.codes import AckCode
from gwc.opcua.answers import OUT, result

V = ua.VariantType
UNRESERVE_ARGS = [("force", V.Boolean, "even while the holder's lot script runs (gwc unreserve --force)")]
UNRESERVE_OUT = [*OUT, ("entity_id", V.Int64, "the lot entity that held the machine")]
MAINTENANCE_OUT = [*OUT, ("runs", V.Int64, "the machine's runs since its last maintenance, before this one")]
# The gateway's: runs one method's call, turning a silent module or a refusal into a status, logged.
Converse = Callable[[str, Callable[[], Awaitable[ua.CallMethodResult]]], Awaitable[ua.CallMethodResult]]


class HiMethods:
    def __init__(
        self, cfg: Config, log: logging.Logger, converse: Converse, by: str, lock: asyncio.Lock | None = None
    ) -> None:
        self.cfg = cfg
        self.log = log
        self.converse = converse
        self.by = by  # who acted, as the cell records it
        self.lock = lock or asyncio.Lock()  # shared with the gateway's Work Order Entry

    async def _call(
        self, what: str, act: Callable[[BlockingBus], ua.CallMethodResult], refused: str
    ) -> ua.CallMethodResult:
        """`act` on an HI bus attachment, in a thread. A Refused answers its ack code; another
        refusal of the client code (a GwcError, which says why) answers `refused`."""

        async def call() -> ua.CallMethodResult:
            def run() -> ua.CallMethodResult:
                with hi_bus(self.cfg, self.log) as bus:
                    return act(bus)

            try:
                async with self.lock:
                    return await asyncio.to_thread(run)
            except ConversationTimeout:
                raise
            except Refused as e:
                return result(e.ack_code, str(e))
            except GwcError as e:
                return result(refused, str(e))

        return await self.converse(what, call)

    async def unreserve(self, machine: str, force: bool) -> ua.CallMethodResult:
        """The operator's unreserve of a machine held by a dead lot: refused (BadInvalidState, saying
        why) when nobody holds it, or while its holder's script runs unless `force`."""

        def act(bus: BlockingBus) -> ua.CallMethodResult:
            entity = unreserve_machine(self.cfg, bus, machine, force, by=self.by)
            return result(
                AckCode.ACK_OK, f"{machine} freed (it was reserved to entity {entity})", ua.Variant(entity, V.Int64)
            )

        return await self._call(f"Unreserve({machine}, force={force})", act, AckCode.NOTNOW)

    async def maintenance_done(self, machine: str) -> ua.CallMethodResult:
        """The machine was maintained: MAINT_DONE to the Machine Server, its count of runs since
        maintenance starts again; answers the count before."""

        def act(bus: BlockingBus) -> ua.CallMethodResult:
            runs = maintenance_done(bus, machine, by=self.by)
            return result(AckCode.ACK_OK, f"{machine} maintained after {runs} run(s)", ua.Variant(runs, V.Int64))

        return await self._call(f"MaintenanceDone({machine})", act, AckCode.UNKNOWN)
