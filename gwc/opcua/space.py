"""The gateway's address space: string node ids in the cell's namespace, named after their path, so a
node keeps its id across restarts of the gateway (docs/opcua.md, Address space).

`Space` adds objects, variables and methods with the type definitions and references it is told
(the companion specifications' types, the cell's own), and writes a value only when it changed (a
subscriber sees a change, not a rewrite of the same value), always with its source timestamp (when
the cell's state changed) and server timestamp (when the gateway learnt it). The layouts below say
which variables each object has, named as the thesis and the tables name them.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from asyncua import Server, ua

V = ua.VariantType
S = ua.StatusCodes
I = ua.ObjectIds  # noqa: E741 (the standard node ids, as asyncua names them)
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
INTEGERS = {
    V.SByte: (-(2**7), 2**7 - 1),
    V.Byte: (0, 2**8 - 1),
    V.Int16: (-(2**15), 2**15 - 1),
    V.UInt16: (0, 2**16 - 1),
    V.Int32: (-(2**31), 2**31 - 1),
    V.UInt32: (0, 2**32 - 1),
    V.Int64: (-(2**63), 2**63 - 1),
    V.UInt64: (0, 2**64 - 1),
}


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


def nid(identifier: int, ns: int = 0) -> ua.NodeId:
    """A numeric node id (asyncua's NodeId wants its own integer types)."""
    return ua.NodeId(ua.Int32(identifier), ua.Int16(ns))


def status(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


def _variant(value: Any, vtype: ua.VariantType) -> ua.Variant:
    if vtype == V.LocalizedText and isinstance(value, str):
        value = ua.LocalizedText(value)
    return ua.Variant(value, vtype)


def data_value(value: Any, vtype: ua.VariantType, source: datetime, server: datetime) -> ua.DataValue:
    """A value with both timestamps. A null (a null column, no run yet) is a DataValue with no value
    at all, which every client reads as Null: asyncua would refuse a Null variant written over a
    typed one (and keep the stale value), and a typed variant cannot hold a null integer."""
    dv = ua.DataValue(
        None if value is None else _variant(value, vtype),
        SourceTimestamp=source,  # type: ignore[arg-type]
        ServerTimestamp=server,  # type: ignore[arg-type]
    )
    if value is None:
        object.__setattr__(dv, "Value", None)  # DataValue turns None into a Null variant; keep it absent
    return dv


def argument(name: str, vtype: ua.VariantType, what: str) -> ua.Argument:
    a = ua.Argument(Name=name, DataType=ua.NodeId(ua.Int32(vtype.value)), Description=ua.LocalizedText(what))
    a.ValueRank = -1
    return a


def check_arguments(
    given: Sequence[ua.Variant], declared: Sequence[tuple[str, ua.VariantType, str]]
) -> ua.CallMethodResult | None:
    """Part 4 (Call): the count, then each argument's type, without converting anything. An integer
    of another width is taken when its value fits the declared type (UaExpert and node-opcua send the
    declared type; asyncua's client sends any Python int as Int64). None: the arguments are good."""
    if len(given) < len(declared):
        return ua.CallMethodResult(StatusCode=status(S.BadArgumentsMissing))
    if len(given) > len(declared):
        return ua.CallMethodResult(StatusCode=status(S.BadTooManyArguments))
    results = []
    for arg, (_, vtype, _) in zip(given, declared):
        good = arg.VariantType == vtype and not arg.is_array
        if not good and vtype in INTEGERS and arg.VariantType in INTEGERS and not arg.is_array:
            low, high = INTEGERS[vtype]
            good = isinstance(arg.Value, int) and low <= arg.Value <= high
        results.append(status(S.Good if good else S.BadTypeMismatch))
    if all(r.is_good() for r in results):
        return None
    return ua.CallMethodResult(StatusCode=status(S.BadInvalidArgument), InputArgumentResults=results)


MethodCallback = Callable[..., Awaitable[ua.CallMethodResult]]


@dataclass(frozen=True)
class Ref:
    """A reference to add: from `source` to `target` of type `kind` (a ua.ObjectIds number)."""

    source: ua.NodeId
    target: ua.NodeId
    kind: int


class Space:
    """Nodes of the namespace `ns`, addressed by path ("machines/cmm_wc/status")."""

    def __init__(self, server: Server, ns: int, log: logging.Logger | None = None) -> None:
        self.server = server
        self.ns = ns
        self.log = log or logging.getLogger(__name__)
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

    def qname(self, name: str | ua.QualifiedName) -> ua.QualifiedName:
        return name if isinstance(name, ua.QualifiedName) else ua.QualifiedName(name, self.ns)

    async def _add(self, items: list[ua.AddNodesItem]) -> None:
        for item, res in zip(items, await self.server.iserver.isession.add_nodes(items)):
            if not res.StatusCode.is_good():
                self.log.error("could not add %s: %s", item.RequestedNewNodeId.to_string(), res.StatusCode.name)
                res.StatusCode.check()

    async def add_object(
        self,
        parent: ua.NodeId,
        path: str,
        name: str | ua.QualifiedName,
        typedef: ua.NodeId | int = I.BaseObjectType,
        ref: int = I.HasComponent,
        display: str | None = None,
    ) -> ua.NodeId:
        qn = self.qname(name)
        attrs = ua.ObjectAttributes(DisplayName=ua.LocalizedText(display or qn.Name), EventNotifier=0)
        item = ua.AddNodesItem(
            ParentNodeId=parent,
            ReferenceTypeId=nid(ref),
            RequestedNewNodeId=self.nodeid(path),
            BrowseName=qn,
            NodeClass=ua.NodeClass.Object,
            NodeAttributes=attrs,
            TypeDefinition=typedef if isinstance(typedef, ua.NodeId) else nid(typedef),
        )
        await self._add([item])
        return self.nodeid(path)

    async def add_variables(
        self,
        parent: ua.NodeId,
        variables: Iterable[tuple[str, str | ua.QualifiedName, ua.VariantType, int]],
        at: datetime | None = None,
        typedef: int | None = None,
    ) -> None:
        """Variables (path, name, type, ua.ObjectIds of the reference: HasComponent for a data
        variable, HasProperty for a property), each Null with both timestamps until written. Their
        type definition is `typedef`, or BaseDataVariableType / PropertyType by the reference."""
        now = at or datetime.now(UTC)
        variables = list(variables)
        items = []
        for path, name, vtype, ref in variables:
            qn = self.qname(name)
            attrs = ua.VariableAttributes(
                DisplayName=ua.LocalizedText(qn.Name),
                DataType=ua.NodeId(ua.Int32(vtype.value)),
                ValueRank=ua.ValueRank.Scalar,
                AccessLevel=ua.AccessLevel.CurrentRead.mask,
                UserAccessLevel=ua.AccessLevel.CurrentRead.mask,
                Value=ua.Variant(),
            )
            vartype = typedef or (I.PropertyType if ref == I.HasProperty else I.BaseDataVariableType)
            items.append(
                ua.AddNodesItem(
                    ParentNodeId=parent,
                    ReferenceTypeId=nid(ref),
                    RequestedNewNodeId=self.nodeid(path),
                    BrowseName=qn,
                    NodeClass=ua.NodeClass.Variable,
                    NodeAttributes=attrs,
                    TypeDefinition=nid(vartype),
                )
            )
            self._types[path] = vtype
        await self._add(items)
        for path, *_ in variables:
            await self._write(path, None, now, now)

    async def add_references(self, refs: Iterable[Ref]) -> None:
        items = [
            ua.AddReferencesItem(
                SourceNodeId=r.source,
                TargetNodeId=r.target,
                ReferenceTypeId=nid(r.kind),
                IsForward=True,
                TargetNodeClass=ua.NodeClass.Object,
            )
            for r in refs
        ]
        for res in await self.server.iserver.isession.add_references(items):
            if not res.is_good():
                raise ua.UaStatusCodeError(res.value)

    async def folder(self, parent: ua.NodeId, path: str, name: str | ua.QualifiedName) -> ua.NodeId:
        return await self.add_object(parent, path, name, I.FolderType, I.Organizes)

    async def object(
        self,
        parent: ua.NodeId,
        path: str,
        name: str | ua.QualifiedName,
        layout: dict[str, ua.VariantType] | None = None,
        typedef: ua.NodeId | int = I.BaseObjectType,
        ref: int = I.HasComponent,
    ) -> ua.NodeId:
        """An object with the data variables of `layout` (all Null until written)."""
        node = await self.add_object(parent, path, name, typedef, ref)
        await self.add_variables(node, [(f"{path}/{v}", v, t, I.HasComponent) for v, t in (layout or {}).items()])
        return node

    async def method(
        self,
        parent: ua.NodeId,
        path: str,
        name: str,
        callback: MethodCallback,
        inputs: Sequence[tuple[str, ua.VariantType, str]],
        outputs: Sequence[tuple[str, ua.VariantType, str]],
    ) -> ua.NodeId:
        """A method with named, described arguments: (name, type, what it is). It answers only when
        called on its own object, with the declared arguments (check_arguments); `callback` then gets
        the arguments' values, as Python values."""
        node = self.server.get_node(parent)

        async def call(object_id: ua.NodeId, *given: ua.Variant) -> ua.CallMethodResult:
            if object_id != parent:  # Part 4: a method is called on the object it is a component of
                self.log.warning("OPC UA method %s called on %s, not on its object", name, object_id.to_string())
                return ua.CallMethodResult(StatusCode=status(S.BadMethodInvalid))
            refused = check_arguments(given, inputs)
            if refused is not None:
                self.log.warning(
                    "OPC UA method %s refused (%s): arguments %s, declared %s",
                    name,
                    refused.StatusCode.name,
                    [(a.VariantType.name, a.Value) for a in given],
                    [(n, t.name) for n, t, _ in inputs],
                )
                return refused
            return await callback(*(a.Value for a in given))

        made = await node.add_method(
            self.nodeid(path),
            ua.QualifiedName(name, self.ns),
            call,
            [argument(*i) for i in inputs],
            [argument(*o) for o in outputs],
        )
        nodeid: ua.NodeId = made.nodeid
        return nodeid

    async def set(self, path: str, value: Any, at: datetime | None = None) -> None:
        """Write a variable if its value changed (subscribers are notified of changes only); `at` is
        when the cell's state changed (its source timestamp), now if not known."""
        if path in self._values and self._values[path] == value:
            return
        now = datetime.now(UTC)
        await self._write(path, value, at or now, now)

    async def _write(self, path: str, value: Any, source: datetime, server: datetime) -> None:
        status = await self.server.iserver.aspace.write_attribute_value(
            self.nodeid(path), ua.AttributeIds.Value, data_value(value, self._types[path], source, server)
        )
        if status.is_good():
            self._values[path] = value
        else:  # not remembered: the next re-read writes it again
            self._values.pop(path, None)
            self.log.warning("could not write %s = %r: %s", path, value, status.name)

    async def set_all(
        self, path: str, row: dict[str, Any], layout: dict[str, ua.VariantType], at: datetime | None = None
    ) -> None:
        for var in layout:
            if var in row:
                await self.set(f"{path}/{var}", row[var], at)

    async def remove(self, path: str) -> None:
        """Delete an object and everything under it."""
        await self.server.delete_nodes([self.server.get_node(self.nodeid(path))], recursive=True)
        prefix = f"{path}/"
        for known in (self._types, self._values):
            for p in [p for p in known if p.startswith(prefix)]:
                del known[p]
