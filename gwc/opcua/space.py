"""The gateway's address space: string node ids in the cell's namespace, named after their path, so a
node keeps its id across restarts of the gateway (docs/opcua.md, Address space).

`Space` adds objects and variables and writes a value only when it changed (a subscriber sees a
change, not a rewrite of the same value). The layouts below say which variables each object has,
named as the thesis and the tables name them (status, machine_run_id, recipe_id, ...).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from asyncua import Node, Server, ua

V = ua.VariantType
# name -> type of the variables of each kind of object (the table's column names).
MACHINE = {
    "status": V.String,
    "machine_run_id": V.Int64,
    "recipe_id": V.String,
    "start_time": V.DateTime,
    "end_time": V.DateTime,
    "note": V.String,
    "runs": V.Int64,
    "runs_since_maintenance": V.Int32,
    "scrap_count": V.Int32,
    "maintenance_every": V.Int32,
    "accepts": V.String,
    "wc_on_bus": V.Boolean,
}
IDENTIFICATION = {"ComponentName": V.String, "Model": V.String, "AssetId": V.String, "Location": V.String}
STATE = {"CurrentState": V.LocalizedText, "CurrentStateNumber": V.UInt32}
LAST_RUN = {
    "machine_run_id": V.Int64,
    "ack_code": V.String,
    "note": V.String,
    "ended_at": V.DateTime,
    "results": V.String,
}
LOT = {
    "lot_id": V.Int64,
    "product_id": V.String,
    "work_order_id": V.Int64,
    "owner": V.String,
    "priority": V.Int32,
    "quantity": V.Int32,
}
ENTITY = {"entity_id": V.Int64, "state": V.String, "reason": V.String, "updated_at": V.DateTime}
ALARM = {
    "alarm_no": V.Int64,
    "alarm_id": V.String,
    "machine_id": V.String,
    "alarm_text": V.String,
    "severity": V.String,
    "raised_by": V.String,
    "raised_at": V.DateTime,
}
STATUS_LINE = {"text": V.String, "imports": V.Int32, "exports": V.Int32, "alarms": V.Int32, "last_event": V.String}

# OPC 40001-1 (Machinery): MachineryItemState and MachineryOperationMode, name -> number.
ITEM_STATES = {"NotAvailable": 0, "OutOfService": 1, "Executing": 2, "NotExecuting": 3}
OPERATION_MODES = {"None": 0, "Maintenance": 1, "Setup": 2, "Processing": 3}


def machinery_state(status: str | None, on_bus: bool) -> str:
    """The Machinery MachineryItemState of a cell status: a machine in Setup, Running or finishing
    either before shutting down is doing something; Idle is not; Shutdown is out of service, or
    not available at all when its WC is not on the bus (its processes are down)."""
    if status in ("Setup", "Running", "Setup_Shut", "Run_Shut"):
        return "Executing"
    if status == "Idle":
        return "NotExecuting"
    return "OutOfService" if status == "Shutdown" and on_bus else "NotAvailable"


def operation_mode(status: str | None) -> str:
    return {"Setup": "Setup", "Setup_Shut": "Setup", "Running": "Processing", "Run_Shut": "Processing"}.get(
        status or "", "None"
    )


def _variant(value: Any, vtype: ua.VariantType) -> ua.Variant:
    if vtype == V.LocalizedText and isinstance(value, str):
        value = ua.LocalizedText(value)
    return ua.Variant(value, vtype)


class Space:
    """Nodes of the namespace `ns`, addressed by path ("machines/cmm_wc/status")."""

    def __init__(self, server: Server, ns: int) -> None:
        self.server = server
        self.ns = ns
        self._types: dict[str, ua.VariantType] = {}
        self._values: dict[str, Any] = {}

    def nodeid(self, path: str) -> ua.NodeId:
        return ua.NodeId(ua.String(path), ua.Int16(self.ns))

    def path_of(self, nodeid: ua.NodeId) -> str | None:
        """The path of one of our node ids, None for another namespace's."""
        return str(nodeid.Identifier) if nodeid.NamespaceIndex == self.ns else None

    def value(self, path: str) -> Any:
        """The value last written to a variable (None if never, or null)."""
        return self._values.get(path)

    def has(self, path: str) -> bool:
        return path in self._values

    async def folder(self, parent: Node, path: str, name: str) -> Node:
        return await parent.add_folder(self.nodeid(path), ua.QualifiedName(name, self.ns))

    async def object(self, parent: Node, path: str, name: str, layout: dict[str, ua.VariantType] | None = None) -> Node:
        """An object with the variables of `layout` (all null until written)."""
        node = await parent.add_object(self.nodeid(path), ua.QualifiedName(name, self.ns))
        for var, vtype in (layout or {}).items():
            await node.add_variable(
                self.nodeid(f"{path}/{var}"), ua.QualifiedName(var, self.ns), ua.Variant(), datatype=vtype.value
            )
            self._types[f"{path}/{var}"] = vtype
            self._values[f"{path}/{var}"] = None
        return node

    async def method(
        self,
        parent: Node,
        path: str,
        name: str,
        callback: Callable[..., Any],
        inputs: Iterable[tuple[str, ua.VariantType, str]],
        outputs: Iterable[tuple[str, ua.VariantType, str]],
    ) -> Node:
        """A method with named, described arguments: (name, type, what it is)."""

        def arg(name: str, vtype: ua.VariantType, what: str) -> ua.Argument:
            a = ua.Argument(Name=name, DataType=ua.NodeId(ua.Int32(vtype.value)), Description=ua.LocalizedText(what))
            a.ValueRank = -1
            return a

        return await parent.add_method(
            self.nodeid(path),
            ua.QualifiedName(name, self.ns),
            callback,
            [arg(*i) for i in inputs],
            [arg(*o) for o in outputs],
        )

    async def set(self, path: str, value: Any) -> None:
        """Write a variable if its value changed (subscribers are notified of changes only)."""
        if path in self._values and self._values[path] == value:
            return
        self._values[path] = value
        # A null column is a DataValue without a value: asyncua refuses a Null variant over a typed one.
        variant = None if value is None else _variant(value, self._types[path])
        await self.server.write_attribute_value(self.nodeid(path), ua.DataValue(variant))

    async def set_all(self, path: str, row: dict[str, Any], layout: dict[str, ua.VariantType]) -> None:
        for var in layout:
            if var in row:
                await self.set(f"{path}/{var}", row[var])

    async def remove(self, path: str) -> None:
        """Delete an object and everything under it."""
        await self.server.delete_nodes([self.server.get_node(self.nodeid(path))], recursive=True)
        prefix = f"{path}/"
        for known in (self._types, self._values):
            for p in [p for p in known if p.startswith(prefix)]:
                del known[p]
