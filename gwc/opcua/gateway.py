"""The OPC UA gateway: a cell module (`gwc run opcua`) serving the cell's state to OPC UA clients.

It owns no table. It learns the cell's state from what it hears on the bus (UPD_ME_ST, RUN_COMPL,
ALARM_CLE, CELL_EVENT, LOT_MOVED) and from the tables it reads as role gwc_opcua; a broadcast makes
it write at once what the broadcast says and re-read what it touches, and every `refresh` seconds
it re-reads everything, so a missed broadcast, or a gateway restarted mid-way, is put right.

Methods hold the same conversations the `gwc` command holds (ME_START, ME_SHUT, ALARM_CLR_REQ,
IMPORT_LOT, EXPORT_LOT, CANCEL_RE; a work order is entered by the HI's own code) and answer with the
cell's ack code as an OPC UA status (docs/opcua.md, Methods).
"""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import re
import time
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from typing import Any

from asyncua import Node, ua
from asyncua.server.event_generator import EventGenerator

from gwc.cell import hi_bus
from gwc.config import Config
from gwc.errors import ConversationTimeout, GwcError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module, module_name
from gwc.opcua import record, security
from gwc.opcua.settings import load_settings
from gwc.opcua.space import (
    ALARM,
    ENTITY,
    IDENTIFICATION,
    ITEM_STATES,
    LAST_RUN,
    LOT,
    MACHINE,
    OPERATION_MODES,
    STATE,
    STATUS_LINE,
    Space,
    machinery_state,
    operation_mode,
)

V = ua.VariantType
S = ua.StatusCodes
LISTENS = (Conv.UPD_ME_ST, Conv.RUN_COMPL, Conv.ALARM_CLE, Conv.CELL_EVENT, Conv.LOT_MOVED)
# The cell's ack codes as OPC UA statuses (docs/opcua.md, Methods).
STATUS_OF: dict[str, int] = {
    AckCode.ACK_OK: S.Good,
    AckCode.NOTNOW: S.BadInvalidState,
    AckCode.UNKNOWN: S.BadNotFound,
    AckCode.REQ_KEY_U: S.BadNotFound,
    AckCode.BAD_MESSAGE: S.BadInvalidArgument,
    AckCode.DB_BADREA: S.BadResourceUnavailable,
    AckCode.DB_BADUPD: S.BadResourceUnavailable,
    AckCode.TIMEOUT: S.BadTimeout,
}
SEVERITY = {"note": 200, "warning": 500, "error": 800}  # OPC UA event severity, 1..1000
# asyncua serves one client connection's requests one after the other, and asyncua's client gives up
# a connection whose server does not answer its probe within 1 s: a method must not hold its client
# longer than this for a machine to finish starting or stopping (a CMM waits to be homed).
COMPLETE_WAIT = 0.5
OUT = [("ack_code", V.String, "the cell's ack code"), ("note", V.String, "what the cell said")]
MethodResult = Awaitable[ua.CallMethodResult]

MACHINES_SQL = """
select s.machine_id, s.status, s.recipe_id, s.machine_run_id, s.start_time, s.end_time, s.note,
       s.runs_since_maintenance, s.scrap_count, s.maintenance_every,
       (select count(*) from machine_run_outcome o where o.machine_id = s.machine_id) as runs,
       coalesce((select string_agg(a.op_type, ',' order by a.op_type) from accept_types a
                 where a.machine_id = s.machine_id), '') as accepts
  from machine_status s where s.machine_id = any(%s)
"""
LAST_RUNS_SQL = """
select distinct on (machine_id) machine_id, machine_run_id, ack_code, note, ended_at
  from machine_run_outcome where machine_id = any(%s) order by machine_id, ended_at desc
"""
RESULTS_SQL = """
select machine_id, param, value from machine_run_result
 where (machine_run_id, machine_id) in (select * from unnest(%s::bigint[], %s::text[])) order by param
"""
ALARMS_SQL = """
select a.alarm_no, a.alarm_id, a.machine_id, a.alarm_text, a.raised_by, a.raised_at,
       coalesce(d.severity, 'warning') as severity
  from alarms a left join alarm_description d using (alarm_id) where a.cleared_at is null order by a.alarm_no
"""
LOTS_SQL = """
select s.entity_id, s.lot_id, s.state, s.reason, s.updated_at, l.product_id, l.work_order_id, l.owner,
       l.priority, l.quantity
  from lot_status s join lots l using (lot_id) join lot_entities e using (entity_id)
 where e.destroyed_at is null
   and (s.state not in ('exported', 'failed') or s.updated_at > now() - make_interval(secs => %s))
"""


def _rows(cur: Any, sql: str, *params: Any) -> list[dict[str, Any]]:
    cur.execute(sql, params)
    cols = [d.name for d in cur.description or []]
    return [dict(zip(cols, r)) for r in cur.fetchall()]


def result(code: str | int, note: str = "", *more: ua.Variant) -> ua.CallMethodResult:
    """A method's answer: the ack code as a status, the code and the note as outputs."""
    status = code if isinstance(code, int) else STATUS_OF.get(code, S.BadUnexpectedError)
    name = code if isinstance(code, str) else ua.StatusCode(ua.UInt32(code)).name
    return ua.CallMethodResult(
        StatusCode=ua.StatusCode(ua.UInt32(status)),
        OutputArguments=[ua.Variant(name, V.String), ua.Variant(note[:500], V.String), *more],
    )


class Gateway(Module):
    role = "opcua"

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.settings = load_settings(cfg)
        self.machine_ids = [m.id for m in cfg.machines]
        self.server: security.GatewayServer | None = None
        self.space: Space | None = None
        self.alarms: dict[int, dict[str, Any]] = {}  # pending alarms, as raised to OPC UA clients
        self.lots: set[int] = set()  # lots in the address space
        self.entities: dict[int, int] = {}  # entity -> lot, as in the address space
        self._alarm_events: EventGenerator | None = None
        self._alarm_template: Any = None
        self._event_lock = asyncio.Lock()
        self._order_lock = asyncio.Lock()
        self._dirty: set[str] = set()
        self._wake = asyncio.Event()
        self._heard: dict[str, int] = dict.fromkeys(self.machine_ids, 0)  # UPD_ME_ST heard per machine
        self._cleared = 0  # ALARM_CLE heard
        self._refresher: asyncio.Task[None] | None = None

    def handlers(self) -> dict[str, Handler]:
        return dict.fromkeys(LISTENS, self.heard)

    # ----------------------------------------------------------------- lifecycle

    async def on_startup(self) -> str:
        await self._open_server()
        await self._refresh({"machines", "alarms", "lots", "status_line"})
        self._refresher = asyncio.get_running_loop().create_task(self._refresh_loop())
        assert self.server is not None
        self.log.info("OPC UA server listening at %s", self.settings.endpoint)
        return AckCode.ACK_OK

    async def on_shutdown(self) -> str | None:
        if self._refresher is not None:
            self._refresher.cancel()
        if self.server is not None:
            await self.server.stop()
            self.server = None
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
        users = security.GatewayUsers(s, self.log)
        await users.load()
        server = security.GatewayServer(user_manager=users)  # type: ignore[arg-type]
        await server.init()
        server.set_server_name(f"GWC cell {self.cfg.cell_name}")
        server.set_endpoint(s.endpoint)
        app_uri = f"urn:gwc:{self.cfg.cell_name}:opcua"
        await server.set_application_uri(app_uri)
        cert, key = await security.server_certificate(s, app_uri)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        server.set_security_policy(security.security_policies(s))
        server.set_identity_tokens(security.identity_tokens(s))
        ns = await server.register_namespace(s.namespace)
        self.server, self.space = server, Space(server, ns)
        await self._build(server.nodes.objects)
        await server.start()

    async def _build(self, objects: Node) -> None:
        """The fixed part of the address space (docs/opcua.md): the cell, its machines, the folders."""
        sp = self.space
        assert sp is not None and self.server is not None
        cell = await sp.object(objects, "cell", "Cell", STATUS_LINE)
        await self.server.write_attribute_value(
            cell.nodeid,
            ua.DataValue(ua.Variant(ua.LocalizedText(f"Cell {self.cfg.cell_name}"))),
            ua.AttributeIds.DisplayName,
        )
        machines = await sp.folder(cell, "machines", "Machines")
        await sp.folder(cell, "lots", "Lots")
        await sp.folder(cell, "alarms", "Alarms")
        for spec in self.cfg.machines:
            path = f"machines/{spec.id}"
            node = await sp.object(machines, path, spec.id, MACHINE)
            ident = {"ComponentName": spec.id, "Model": spec.kind, "AssetId": spec.id, "Location": self.cfg.cell_name}
            await sp.object(node, f"{path}/Identification", "Identification", IDENTIFICATION)
            await sp.set_all(f"{path}/Identification", ident, IDENTIFICATION)
            await sp.object(node, f"{path}/MachineryItemState", "MachineryItemState", STATE)
            await sp.object(node, f"{path}/MachineryOperationMode", "MachineryOperationMode", STATE)
            await sp.object(node, f"{path}/last_run", "last_run", LAST_RUN)
            await sp.set(f"{path}/wc_on_bus", False)
            await self._item_state(spec.id)
            await sp.method(node, f"{path}/Start", "Start", self.start_machine, [], OUT)
            await sp.method(node, f"{path}/Stop", "Stop", self.stop_machine, [], OUT)
            await record.build(self, node, spec.id, OUT)  # OEE and open downtime (docs/record.md)
        await sp.method(
            cell,
            "cell/EnterWorkOrder",
            "EnterWorkOrder",
            self.enter_work_order,
            [
                ("customer", V.String, "customer id (gwc customer list)"),
                ("items", V.String, "PRODUCT=QTY items, separated by spaces or commas"),
                ("priority", V.Int32, "priority of its lots; 0 for the default"),
            ],
            [*OUT, ("work_order_id", V.Int64, "the new work order")],
        )
        entity = [("entity_id", V.Int64, "the lot entity")]
        await sp.method(cell, "cell/ImportLot", "ImportLot", self.import_lot, entity, OUT)
        await sp.method(cell, "cell/ExportLot", "ExportLot", self.export_lot, entity, OUT)
        await sp.method(
            cell,
            "cell/CancelRequest",
            "CancelRequest",
            self.cancel_request,
            [("request_key", V.Int64, "the machine request (gwc requests)")],
            OUT,
        )
        await sp.method(
            cell, "cell/ClearAlarm", "ClearAlarm", self.clear_alarm, [("alarm_no", V.Int64, "the alarm")], OUT
        )
        # Alarms are AlarmConditionType events emitted by the Server object (where clients subscribe
        # to events); each is a condition whose ConditionId is its node under Alarms.
        self._alarm_events = await self.server.get_event_generator(ua.ObjectIds.AlarmConditionType, ua.ObjectIds.Server)
        self._alarm_template = copy.copy(self._alarm_events.event)
        self.server.link_method(
            self.server.get_node(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge), self.acknowledge
        )

    # ----------------------------------------------------------------- what the gateway hears

    async def heard(self, conv: Conversation) -> None:
        """A broadcast: write what it says at once, and re-read what it touches."""
        msg = conv.first.first if conv.first else None
        if msg is None or self.space is None:
            return
        if conv.cls == Conv.UPD_ME_ST and msg.machine_id in self._heard:
            self._heard[msg.machine_id] += 1
            path = f"machines/{msg.machine_id}"
            await self.space.set(f"{path}/status", msg.status)
            await self.space.set(f"{path}/machine_run_id", msg.machine_run_id)
            await self._item_state(msg.machine_id)
            self._poke("machines", "status_line")
        elif conv.cls == Conv.ALARM_CLE:
            self._cleared += 1
            await self._alarm_cleared(int(msg.alarm_no), f"cleared by {msg.cleared_by}")
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
        return await asyncio.to_thread(self.transaction, fn)

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
            machines = _rows(cur, MACHINES_SQL, self.machine_ids)
            last = _rows(cur, LAST_RUNS_SQL, self.machine_ids)
            results = _rows(cur, RESULTS_SQL, [r["machine_run_id"] for r in last], [r["machine_id"] for r in last])
            return machines, last, results

        machines, last, results = await self._read(read)
        for row in machines:
            m = row["machine_id"]
            if self._heard[m] != heard[m]:  # a newer UPD_ME_ST came while we read: the next refresh
                self._poke("machines")
                continue
            await sp.set_all(f"machines/{m}", row, MACHINE)
            await self._item_state(m)
        for row in last:
            m = row["machine_id"]
            res = {r["param"]: r["value"] for r in results if r["machine_id"] == m}
            await sp.set_all(f"machines/{m}/last_run", {**row, "results": json.dumps(res)}, LAST_RUN)

    async def _item_state(self, machine_id: str) -> None:
        """The Machinery-style states of a machine, from its cell status and its WC's presence."""
        sp = self.space
        assert sp is not None
        path = f"machines/{machine_id}"
        status = sp.value(f"{path}/status")
        state = machinery_state(status, bool(sp.value(f"{path}/wc_on_bus")))
        mode = operation_mode(status)
        await sp.set_all(
            f"{path}/MachineryItemState", {"CurrentState": state, "CurrentStateNumber": ITEM_STATES[state]}, STATE
        )
        await sp.set_all(
            f"{path}/MachineryOperationMode", {"CurrentState": mode, "CurrentStateNumber": OPERATION_MODES[mode]}, STATE
        )

    async def _refresh_alarms(self) -> None:
        cleared = self._cleared
        rows = await self._read(lambda cur: _rows(cur, ALARMS_SQL))
        if cleared != self._cleared:  # an ALARM_CLE came while we read
            self._poke("alarms")
            return
        pending = {int(r["alarm_no"]): r for r in rows}
        for no in [n for n in self.alarms if n not in pending]:
            await self._alarm_cleared(no, "cleared")
        for no, row in pending.items():
            if no not in self.alarms:
                await self._alarm_raised(row)

    async def _alarm_raised(self, row: dict[str, Any]) -> None:
        sp = self.space
        assert sp is not None
        no = int(row["alarm_no"])
        self.alarms[no] = row
        await sp.object(sp.server.get_node(sp.nodeid("alarms")), f"alarms/{no}", f"alarm_{no}", ALARM)
        await sp.set_all(f"alarms/{no}", row, ALARM)
        await self._alarm_event(row, active=True, text=row["alarm_text"], at=row["raised_at"])
        self.log.info("alarm %d %s raised to OPC UA clients", no, row["alarm_id"])

    async def _alarm_cleared(self, alarm_no: int, how: str) -> None:
        row = self.alarms.pop(alarm_no, None)
        if row is None or self.space is None:
            return
        await self._alarm_event(row, active=False, text=f"{row['alarm_text']} ({how})", at=datetime.now(UTC))
        await self.space.remove(f"alarms/{alarm_no}")
        self.log.info("alarm %d %s %s: told OPC UA clients", alarm_no, row["alarm_id"], how)

    async def _alarm_event(self, row: dict[str, Any], active: bool, text: str, at: datetime) -> None:
        """One AlarmConditionType event: raised = active and unacknowledged, retained (ConditionRefresh
        sends it again); cleared = inactive and acknowledged (the cell clears and acknowledges at once)."""
        sp = self.space
        assert sp is not None and self._alarm_events is not None
        machine = row["machine_id"]
        ev = copy.copy(self._alarm_template)
        ev.SourceNode = sp.nodeid(f"machines/{machine}" if machine in self._heard else "cell")
        ev.SourceName = machine or "cell"
        ev.NodeId = sp.nodeid(f"alarms/{row['alarm_no']}")
        ev.ConditionName = row["alarm_id"] or "unknown"
        ev.Severity = SEVERITY.get(row["severity"], 500)
        ev.Retain = active
        for state, on, (yes, no) in (
            ("EnabledState", True, ("Enabled", "Disabled")),
            ("ActiveState", active, ("Active", "Inactive")),
            ("AckedState", not active, ("Acknowledged", "Unacknowledged")),
        ):
            setattr(ev, state, ua.LocalizedText(yes if on else no))
            setattr(ev, f"{state}/Id", on)
        async with self._event_lock:  # the generator holds one event at a time
            self._alarm_events.event = ev
            await self._alarm_events.trigger(at, text)

    async def _refresh_lots(self) -> None:
        sp = self.space
        assert sp is not None
        rows = await self._read(lambda cur: _rows(cur, LOTS_SQL, self.settings.keep_done))
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
                await sp.object(sp.server.get_node(sp.nodeid("lots")), lot_path, f"lot_{lot}", LOT)
                self.lots.add(lot)
            await sp.set_all(lot_path, row, LOT)
            path = f"{lot_path}/{entity}"
            if entity not in self.entities:
                await sp.object(sp.server.get_node(sp.nodeid(lot_path)), path, f"entity_{entity}", ENTITY)
                self.entities[entity] = lot
            await sp.set_all(path, row, ENTITY)

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
        await sp.set_all("cell", {k: line.fields.get(k) for k in STATUS_LINE}, STATUS_LINE)

    # ----------------------------------------------------------------- methods

    def _machine_of(self, parent: ua.NodeId) -> str | None:
        path = self.space.path_of(parent) if self.space else None
        m = path.removeprefix("machines/") if path else None
        return m if m in self._heard else None

    async def _converse(self, what: str, call: Callable[[], Awaitable[ua.CallMethodResult]]) -> ua.CallMethodResult:
        """Run one method's conversation; a silent module or a refusal becomes a status, logged."""
        try:
            out = await call()
        except ConversationTimeout as e:
            out = result(AckCode.TIMEOUT, str(e))
        except GwcError as e:
            out = result(AckCode.BAD_MESSAGE, str(e))
        code = out.OutputArguments[0].Value if out.OutputArguments else out.StatusCode.name
        self.log.info(
            "OPC UA method %s: %s %s", what, code, out.OutputArguments[1].Value if out.OutputArguments else ""
        )
        return out

    async def _ask(self, cls: str, first: Message, to: str) -> ua.CallMethodResult:
        answer = await self.ask(cls, first, to, timeout=self.settings.method_timeout)
        return result(answer.ack_code, answer.fields.get("note") or "")

    async def _machine_conversation(
        self, parent: ua.NodeId, cls: str, opener: str, done: tuple[str, ...]
    ) -> ua.CallMethodResult:
        """ME_START / ME_SHUT with a machine's WC, as `gwc machine start|stop` holds it. A machine that
        takes longer than COMPLETE_WAIT (a CMM waiting to be homed, a run to finish first) answers
        GoodCompletesAsynchronously: the change will show in its status."""
        machine = self._machine_of(parent)
        if machine is None:
            return result(AckCode.UNKNOWN, f"no machine at {parent.to_string()}")
        wc = module_name("wc", machine)
        if wc not in self.bus.peers():
            return result(AckCode.NOTNOW, f"{wc} is not on the bus: start its processes (gwc machine start {machine})")
        conv, batch = await self.bus.request(
            cls, message(opener, module=wc), to=wc, timeout=self.settings.method_timeout
        )
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

    async def start_machine(self, parent: ua.NodeId) -> ua.CallMethodResult:
        return await self._converse(
            "Start",
            lambda: self._machine_conversation(
                parent, Conv.ME_START, Msg.STARTUP_REQUEST, (Msg.STARTUP_COMPLETE, Msg.ME_READY)
            ),
        )

    async def stop_machine(self, parent: ua.NodeId) -> ua.CallMethodResult:
        return await self._converse(
            "Stop",
            lambda: self._machine_conversation(
                parent, Conv.ME_SHUT, Msg.SHUTDOWN_REQUEST, (Msg.SHUTDOWN_COMPLETE, Msg.ME_STOPPED)
            ),
        )

    def _by(self) -> str:
        return f"opcua:{self.cfg.cell_name}"

    async def clear_alarm(self, parent: ua.NodeId, alarm_no: ua.Variant) -> ua.CallMethodResult:
        return await self._converse(
            f"ClearAlarm({alarm_no.Value})",
            lambda: self._ask(
                Conv.ALARM_CLR_REQ,
                message(Msg.ALARM_CLEAR_REQUEST, alarm_no=int(alarm_no.Value), cleared_by=self._by()),
                "cas",
            ),
        )

    async def acknowledge(self, condition: ua.NodeId, event_id: ua.Variant, comment: ua.Variant) -> ua.CallMethodResult:
        """The standard Acknowledge of a condition: the cell's alarm is cleared (ALARM_CLR_REQ)."""
        path = self.space.path_of(condition) if self.space else None
        m = re.fullmatch(r"alarms/(\d+)", path or "")
        if m is None:
            return result(S.BadNodeIdUnknown, f"{condition.to_string()} is not one of the cell's alarms")
        return await self.clear_alarm(condition, ua.Variant(int(m.group(1)), V.Int64))

    async def _decide(self, action: str, entity_id: ua.Variant) -> ua.CallMethodResult:
        cls = Conv.IMPORT_LOT if action == "import" else Conv.EXPORT_LOT
        first = message(Msg.LOT_DECISION, entity_id=int(entity_id.Value), action=action, by=self._by())
        return await self._converse(f"{action} entity {entity_id.Value}", lambda: self._ask(cls, first, "ls"))

    async def import_lot(self, parent: ua.NodeId, entity_id: ua.Variant) -> ua.CallMethodResult:
        return await self._decide("import", entity_id)

    async def export_lot(self, parent: ua.NodeId, entity_id: ua.Variant) -> ua.CallMethodResult:
        return await self._decide("export", entity_id)

    async def cancel_request(self, parent: ua.NodeId, request_key: ua.Variant) -> ua.CallMethodResult:
        first = message(Msg.CANCEL_REQUEST, request_key=int(request_key.Value), by=self._by())
        return await self._converse(
            f"CancelRequest({request_key.Value})", lambda: self._ask(Conv.CANCEL_RE, first, "msched")
        )

    async def enter_work_order(
        self, parent: ua.NodeId, customer: ua.Variant, items: ua.Variant, priority: ua.Variant
    ) -> ua.CallMethodResult:
        """Work Order Entry by the HI's own code (it writes WORK_ORDERS as the HI, the table's owner,
        asks the Lot Server for the lots and starts their lot scripts), in a thread: it is blocking."""
        from gwc.client.orders import enter_order, parse_items

        async def enter() -> ua.CallMethodResult:
            parsed = parse_items(tuple(re.split(r"[\s,]+", str(items.Value or "").strip())))
            prio = int(priority.Value) if priority.Value else None

            def run() -> dict[str, Any]:
                with hi_bus(self.cfg, self.log) as bus:
                    return enter_order(self.cfg, self.log, bus, str(customer.Value), parsed, priority=prio)

            async with self._order_lock:  # one HI bus attachment (hi.<pid>) at a time
                made = await asyncio.to_thread(run)
            note = "; ".join(
                f"lot {lot['lot_id']}: {lot['quantity']} x {lot['product_id']} (entities "
                + ", ".join(map(str, lot["entities"]))
                + ")"
                for lot in made["lots"]
            )
            return result(AckCode.ACK_OK, note, ua.Variant(made["work_order_id"], V.Int64))

        return await self._converse(f"EnterWorkOrder({customer.Value}, {items.Value})", enter)
