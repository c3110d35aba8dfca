"""The OPC UA gateway: a cell module (`gwc run opcua`) serving the cell's state to OPC UA clients.

It owns no table. It learns the cell's state from what it hears on the bus (UPD_ME_ST, RUN_COMPL,
ALARM_CLE, CELL_EVENT, LOT_MOVED) and from the tables it reads as role gwc_opcua; a broadcast makes
it write at once what the broadcast says and re-read what it touches, and every `refresh` seconds
it re-reads everything, so a missed broadcast, or a gateway restarted mid-way, is put right.

Methods (gwc/opcua/methods.py) hold the same conversations the `gwc` command holds (ME_START, ME_SHUT, ALARM_CLR_REQ,
IMPORT_LOT, EXPORT_LOT, CANCEL_RE; a work order, a machine's unreserve (UNRESERVE) and its
maintenance (MAINT_DONE) are done by the HI's own client code) and answer with the cell's ack code
as an OPC UA status (docs/opcua.md, Methods).
"""

from __future__ import annotations

import asyncio
import functools
import importlib.metadata
import json
import logging
import time
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import ua

from gwc.config import Config
from gwc.errors import ConversationTimeout, GwcError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module, module_name
from gwc.opcua import model, record, security, store
from gwc.opcua.answers import OUT
from gwc.opcua.conditions import AlarmConditions
from gwc.opcua.door import OpcuaDoor
from gwc.opcua.hi_methods import MAINTENANCE_OUT, UNRESERVE_ARGS, UNRESERVE_OUT, HiMethods
from gwc.opcua.methods import PRIORITIES, CellMethods
from gwc.opcua.settings import load_settings
from gwc.opcua.space import (
    ENTITY,
    LAST_RUN,
    LOT,
    MACHINE,
    STATUS_LINE,
    Space,
    machinery_state,
    nid,
    operation_mode,
)

V = ua.VariantType
S = ua.StatusCodes
LISTENS = (Conv.UPD_ME_ST, Conv.RUN_COMPL, Conv.ALARM_CLE, Conv.CELL_EVENT, Conv.LOT_MOVED)
MethodResult = Awaitable[ua.CallMethodResult]
READ_DRAIN = 5.0  # s the shutdown waits for a read of the tables in progress


def build_info() -> tuple[str, str, datetime]:
    """The gateway's version, build number and build date: the gwc package's version, asyncua's,
    and when this copy of the package was installed or checked out (its __init__'s time)."""
    import gwc

    try:
        version = importlib.metadata.version("gwc")
        asyncua_version = importlib.metadata.version("asyncua")
    except importlib.metadata.PackageNotFoundError:
        version, asyncua_version = "unknown", "unknown"
    built = datetime.fromtimestamp(Path(gwc.__file__).stat().st_mtime, UTC)
    return version, f"gwc {version} on asyncua {asyncua_version}", built


class Gateway(Module):
    role = "opcua"

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.settings = load_settings(cfg)
        self.machine_ids = [m.id for m in cfg.machines]
        self.identification = {m.id: model.identification(cfg.cell_name, m) for m in cfg.machines}
        self.server: security.GatewayServer | None = None
        self.space: Space | None = None
        self.companion: model.Companion | None = None
        self.types: model.CellTypes | None = None
        self.conditions: AlarmConditions | None = None  # pending alarms, as raised to OPC UA clients
        self.lots: set[int] = set()  # lots in the address space
        self.entities: dict[int, int] = {}  # entity -> lot, as in the address space
        self.door = OpcuaDoor(cfg, log)  # cell users, the role table, the audit trail (docs/users.md)
        self.methods = CellMethods(cfg, log, self.bus, self.settings.method_timeout, self.door)
        self.hi = HiMethods(cfg, log, self.methods.converse, self.methods.by, self.methods.lock)
        self._dirty: set[str] = set()
        self._wake = asyncio.Event()
        self._heard: dict[str, int] = dict.fromkeys(self.machine_ids, 0)  # UPD_ME_ST heard per machine
        self._cleared = 0  # ALARM_CLE heard
        self._refresher: asyncio.Task[None] | None = None
        self._reading: asyncio.Future[Any] | None = None  # the read of the tables in its thread, if any

    def handlers(self) -> dict[str, Handler]:
        return dict.fromkeys(LISTENS, self.heard)

    # ----------------------------------------------------------------- lifecycle

    async def on_startup(self) -> str:
        began = time.monotonic()
        await self._open_server()
        await self._refresh({"machines", "alarms", "lots", "status_line"})
        self._refresher = asyncio.get_running_loop().create_task(self._refresh_loop())
        assert self.server is not None and self.companion is not None
        self.log.info(
            "OPC UA server listening at %s (built in %.2f s, of which the companion nodesets %.2f s)",
            self.settings.endpoint,
            time.monotonic() - began,
            self.companion.seconds,
        )
        return AckCode.ACK_OK

    async def on_shutdown(self) -> str | None:
        if self._refresher is not None:
            self._refresher.cancel()
        if self._reading is not None and not self._reading.done():
            # The module closes its connection once this returns: not while a read still uses it in
            # its thread (that held the process's exit for seconds past "Stopped").
            await asyncio.wait({self._reading}, timeout=READ_DRAIN)
        if self.server is not None:
            began = time.monotonic()
            await self.server.stop()
            self.server = None
            self.log.info("OPC UA server stopped in %.2f s", time.monotonic() - began)
        await asyncio.to_thread(self.door.close)
        return None

    async def on_idle(self) -> None:
        if not self.started or self.space is None:
            return
        peers = self.bus.peers()
        for m in self.machine_ids:
            on_bus = module_name("wc", m) in peers
            await self.space.set(f"machines/{m}/wc_on_bus", on_bus)
            await self._item_state(m)
        self._poke("lots")

    async def _open_server(self) -> None:
        """Build the asyncua server: endpoints, security, the address space; then listen."""
        s = self.settings
        users = security.GatewayUsers(s, self.log, self.door)
        await users.load()
        server = security.GatewayServer(user_manager=users)  # type: ignore[arg-type]
        server.iserver.bind_condition_methods = True  # ConditionRefresh replays the retained conditions
        server.product_uri = security.PRODUCT_URI
        server.manufacturer_name = "GWC (Generic WorkCell) project"
        await server.init()
        server.set_server_name(f"GWC cell {self.cfg.cell_name}")
        version, build_number, built = build_info()
        await server.set_build_info(
            security.PRODUCT_URI, server.manufacturer_name, "GWC OPC UA gateway", version, build_number, built
        )
        server.set_endpoint(s.endpoint)
        app_uri = f"urn:gwc:{self.cfg.cell_name}:opcua"
        await server.set_application_uri(app_uri)
        cert, key = await security.server_certificate(s, app_uri)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        server.set_security_policy(security.security_policies(s))
        server.set_identity_tokens(security.identity_tokens(s))
        self.companion = await model.load_companion(server, self.log)
        ns = await server.register_namespace(s.namespace)
        self.server, self.space = server, Space(server, ns, self.log)
        self.types = await model.define_types(self.space)
        await self._build()
        await server.start()

    async def _build(self) -> None:
        """The fixed part of the address space (docs/opcua.md): the cell, its machines, the folders."""
        sp, companion, types = self.space, self.companion, self.types
        assert sp is not None and self.server is not None and companion is not None and types is not None
        objects = nid(ua.ObjectIds.ObjectsFolder)
        cell = await sp.add_object(
            objects, "cell", "Cell", types.cell, ua.ObjectIds.Organizes, f"Cell {self.cfg.cell_name}"
        )
        await sp.add_variables(cell, [(f"cell/{v}", v, t, ua.ObjectIds.HasComponent) for v, t in STATUS_LINE.items()])
        await sp.folder(cell, "lots", "Lots")
        await sp.folder(cell, "alarms", "Alarms")
        machine_methods = [
            model.MachineMethod("Start", self.methods.start_machine, [], OUT),
            model.MachineMethod("Stop", self.methods.stop_machine, [], OUT),
            model.MachineMethod("Unreserve", self.hi.unreserve, UNRESERVE_ARGS, UNRESERVE_OUT),
            model.MachineMethod("MaintenanceDone", self.hi.maintenance_done, [], MAINTENANCE_OUT),
        ]
        for spec in self.cfg.machines:
            methods = [
                model.MachineMethod(m.name, functools.partial(m.callback, spec.id), m.inputs, m.outputs)
                for m in machine_methods
            ]
            await model.build_machine(sp, companion, types, spec, self.identification[spec.id], methods)
            await sp.set(f"machines/{spec.id}/wc_on_bus", False)
            await self._item_state(spec.id)
            # OEE and open downtime (docs/record.md), in the machine's Monitoring object
            await record.build(self, sp.nodeid(f"machines/{spec.id}"), spec.id, OUT)
        await sp.method(
            cell,
            "cell/EnterWorkOrder",
            "EnterWorkOrder",
            self.methods.enter_work_order,
            [
                ("customer", V.String, "customer id (gwc customer list)"),
                ("items", V.String, "PRODUCT=QTY items, separated by spaces or commas"),
                ("priority", V.Int32, f"priority of its lots, {PRIORITIES[0]}..{PRIORITIES[1]}; 0 for the default"),
            ],
            [*OUT, ("work_order_id", V.Int64, "the new work order")],
        )
        entity = [("entity_id", V.Int64, "the lot entity (1 or more)")]
        await sp.method(cell, "cell/ImportLot", "ImportLot", self.methods.import_lot, entity, OUT)
        await sp.method(cell, "cell/ExportLot", "ExportLot", self.methods.export_lot, entity, OUT)
        await sp.method(
            cell,
            "cell/CancelRequest",
            "CancelRequest",
            self.methods.cancel_request,
            [("request_key", V.Int64, "the machine request (gwc requests; 1 or more)")],
            OUT,
        )
        await sp.method(
            cell,
            "cell/ClearAlarm",
            "ClearAlarm",
            self.methods.clear_alarm,
            [("alarm_no", V.Int64, "the alarm (1 or more): clearing HOME_CMM homes and starts the CMM")],
            OUT,
        )
        # Alarms are AlarmConditionType events emitted by the Server object (where clients subscribe
        # to events); each is a condition whose ConditionId is its node under Alarms.
        self.conditions = await AlarmConditions.serve(self.server, sp, types, self.machine_ids, self.log)

    # ----------------------------------------------------------------- what the gateway hears

    async def heard(self, conv: Conversation) -> None:
        """A broadcast: write what it says at once, and re-read what it touches."""
        msg = conv.first.first if conv.first else None
        if msg is None or self.space is None:
            return
        if conv.cls == Conv.UPD_ME_ST and msg.machine_id in self._heard:
            at = datetime.now(UTC)  # the Machine Server broadcasts it as it commits the change
            self._heard[msg.machine_id] += 1
            path = f"machines/{msg.machine_id}"
            await self.space.set(f"{path}/status", msg.status, at)
            await self.space.set(f"{path}/machine_run_id", msg.machine_run_id, at)
            await self._item_state(msg.machine_id, at)
            self._poke("machines", "status_line")
        elif conv.cls == Conv.ALARM_CLE:
            self._cleared += 1
            if self.conditions is not None:
                await self.conditions.cleared(int(msg.alarm_no), f"cleared by {msg.cleared_by}")
            self._poke("alarms", "status_line")
        elif conv.cls == Conv.RUN_COMPL:
            self._poke("machines", "status_line")
        elif conv.cls == Conv.LOT_MOVED:
            self._poke("lots", "status_line")
        else:  # CELL_EVENT: a new alarm, among others
            self._poke("alarms", "status_line")

    def _poke(self, *what: str) -> None:
        self._dirty.update(what)
        self._wake.set()

    async def _refresh_loop(self) -> None:
        last_full = time.monotonic()
        while True:
            try:
                await asyncio.wait_for(self._wake.wait(), timeout=self.settings.refresh)
            except TimeoutError:
                pass
            self._wake.clear()
            if time.monotonic() - last_full >= self.settings.refresh:
                self._dirty.update(("machines", "alarms", "lots", "status_line"))
                last_full = time.monotonic()
            what, self._dirty = self._dirty, set()
            try:
                await self._refresh(what)
            except GwcError as e:  # the database is away: say so, keep serving what we have
                self.log.warning("could not refresh %s: %s", ", ".join(sorted(what)), e)
            except Exception:
                self.log.exception("refreshing %s failed", ", ".join(sorted(what)))

    async def _read(self, fn: Callable[[Any], Any]) -> Any:
        """One read of the tables, in a thread: the OPC UA server shares this event loop, and its
        notifications must not wait while PostgreSQL answers. Only the refresher reads, one read at a
        time, so the module's one connection is never used by two threads at once."""
        self._reading = asyncio.get_running_loop().run_in_executor(None, self.transaction, fn)
        return await asyncio.shield(self._reading)  # cancelled, the refresher leaves the read to end

    async def _refresh(self, what: set[str]) -> None:
        if "machines" in what:
            await self._refresh_machines()
            await record.refresh(self)
        if "alarms" in what:
            await self._refresh_alarms()
        if "lots" in what:
            await self._refresh_lots()
        if "status_line" in what:
            await self._refresh_status_line()

    async def _refresh_machines(self) -> None:
        sp = self.space
        assert sp is not None
        heard = dict(self._heard)

        def read(cur: Any) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
            machines = store.rows(cur, store.MACHINES_SQL, self.machine_ids)
            last = store.rows(cur, store.LAST_RUNS_SQL, self.machine_ids)
            results = store.rows(
                cur, store.RESULTS_SQL, [r["machine_run_id"] for r in last], [r["machine_id"] for r in last]
            )
            return machines, last, results

        machines, last, results = await self._read(read)
        for row in machines:
            m = row["machine_id"]
            if self._heard[m] != heard[m]:  # a newer UPD_ME_ST came while we read: the next refresh
                self._poke("machines")
                continue
            await sp.set_all(f"machines/{m}", row, MACHINE, row["updated_at"])
            await self._item_state(m, row["updated_at"])
        for row in last:
            m = row["machine_id"]
            res = {r["param"]: r["value"] for r in results if r["machine_id"] == m}
            await sp.set_all(f"machines/{m}/last_run", {**row, "results": json.dumps(res)}, LAST_RUN, row["ended_at"])

    async def _item_state(self, machine_id: str, at: datetime | None = None) -> None:
        """The Machinery states of a machine, from its cell status and its WC's presence."""
        sp, companion = self.space, self.companion
        assert sp is not None and companion is not None
        path = f"machines/{machine_id}"
        status = sp.value(f"{path}/status")
        state = machinery_state(status, bool(sp.value(f"{path}/wc_on_bus")))
        await model.set_state(sp, f"{path}/MachineryItemState", companion.item_state, state, at)
        await model.set_state(
            sp, f"{path}/MachineryOperationMode", companion.operation_mode, operation_mode(status), at
        )

    async def _refresh_alarms(self) -> None:
        cleared = self._cleared
        rows = await self._read(lambda cur: store.rows(cur, store.ALARMS_SQL))
        if cleared != self._cleared:  # an ALARM_CLE came while we read
            self._poke("alarms")
            return
        assert self.conditions is not None
        await self.conditions.refresh(rows)

    async def _refresh_lots(self) -> None:
        sp, types = self.space, self.types
        assert sp is not None and types is not None
        rows = await self._read(lambda cur: store.rows(cur, store.LOTS_SQL, self.settings.keep_done))
        now = {int(r["entity_id"]): r for r in rows}
        for entity, lot in list(self.entities.items()):
            if entity not in now or int(now[entity]["lot_id"]) != lot:
                await sp.remove(f"lots/{lot}/{entity}")
                del self.entities[entity]
        lots_now = {int(r["lot_id"]) for r in rows}
        for lot in self.lots - lots_now:
            await sp.remove(f"lots/{lot}")
        self.lots &= lots_now
        for entity, row in sorted(now.items()):
            lot = int(row["lot_id"])
            lot_path = f"lots/{lot}"
            if lot not in self.lots:
                await sp.object(sp.nodeid("lots"), lot_path, f"lot_{lot}", LOT, types.lot, ua.ObjectIds.Organizes)
                self.lots.add(lot)
            await sp.set_all(lot_path, row, LOT, row["updated_at"])
            path = f"{lot_path}/{entity}"
            if entity not in self.entities:
                await sp.object(sp.nodeid(lot_path), path, f"entity_{entity}", ENTITY, types.entity)
                self.entities[entity] = lot
            await sp.set_all(path, row, ENTITY, row["updated_at"])

    async def _refresh_status_line(self) -> None:
        sp = self.space
        assert sp is not None
        if "sls" not in self.bus.peers():
            await sp.set("cell/text", "status line unavailable: the Status Line Server is not on the bus")
            return
        try:
            conv, batch = await self.bus.request(Conv.STATUS_LN, message(Msg.STATUS_LINE_GET), to="sls", timeout=2.0)
            conv.end()
        except ConversationTimeout:
            return
        line = batch.first
        # Every field of the line is written: one the server leaves out is Null, not the last value.
        await sp.set_all("cell", {k: line.fields.get(k) for k in STATUS_LINE}, STATUS_LINE)
