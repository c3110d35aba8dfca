"""The information model: the companion specifications loaded from their published NodeSet2 files
(OPC 10000-100 DI, OPC 10000-200 IA, OPC 40001-1 Machinery: gwc/opcua/nodesets/), the cell's own
types in its own namespace, and one machine's node tree as a Machinery machine (docs/opcua.md).

`build_machine` builds one machine: a module that has more to show of a machine adds it there (or
after it, under the machine's node id `machines/<id>`), and to MACHINE_TYPE so the type says it too.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from gwc.config import MachineSpec
from gwc.errors import ConfigError
from gwc.opcua.space import ALARM, ENTITY, LAST_RUN, LOT, MACHINE, STATUS_LINE, MethodCallback, Ref, Space, nid

V = ua.VariantType
I = ua.ObjectIds  # noqa: E741
NODESETS = Path(__file__).with_name("nodesets")
# In the order they depend on each other (each file's RequiredModel).
NODESET_FILES = ("Opc.Ua.Di.NodeSet2.xml", "Opc.Ua.IA.NodeSet2.xml", "Opc.Ua.Machinery.NodeSet2.xml")
DI_URI = "http://opcfoundation.org/UA/DI/"
MACHINERY_URI = "http://opcfoundation.org/UA/Machinery/"
# Node ids the Machinery nodeset gives these (its own namespace).
MACHINES_FOLDER = 1001
ITEM_STATE_TYPE = 1002
OPERATION_MODE_TYPE = 1008
MACHINE_IDENTIFICATION_TYPE = 1012
HAS_ADD_IN = 17604  # Part 5's HasAddIn (1.04+)
MANDATORY = I.ModellingRule_Mandatory
# [[machine]] identification keys -> (BrowseName, its namespace, type, mandatory): the properties of
# Machinery's MachineIdentificationType (with its DI and Machinery interfaces) the gateway fills.
IDENTIFICATION: dict[str, tuple[str, str, ua.VariantType, bool]] = {
    "manufacturer": ("Manufacturer", DI_URI, V.LocalizedText, True),
    "serial_number": ("SerialNumber", DI_URI, V.String, True),
    "product_instance_uri": ("ProductInstanceUri", DI_URI, V.String, True),
    "manufacturer_uri": ("ManufacturerUri", DI_URI, V.String, False),
    "model": ("Model", DI_URI, V.LocalizedText, False),
    "product_code": ("ProductCode", DI_URI, V.String, False),
    "hardware_revision": ("HardwareRevision", DI_URI, V.String, False),
    "software_revision": ("SoftwareRevision", DI_URI, V.String, False),
    "device_class": ("DeviceClass", DI_URI, V.String, False),
    "year_of_construction": ("YearOfConstruction", MACHINERY_URI, V.UInt16, False),
    "month_of_construction": ("MonthOfConstruction", MACHINERY_URI, V.Byte, False),
    "component_name": ("ComponentName", DI_URI, V.LocalizedText, False),
    "asset_id": ("AssetId", DI_URI, V.String, False),
    "location": ("Location", MACHINERY_URI, V.String, False),
}
_DESIGN_TOOL_ONLY = re.compile(r'<(UA\w+) [^>]*DesignToolOnly="true"[^>]*>.*?</\1>', re.S)


def published_nodeset(name: str) -> str:
    """A vendored NodeSet2 file as published, less its DesignToolOnly nodes (Part 6 F.3: for design
    tools, not a server's address space; asyncua cannot add them: they have no parent)."""
    return _DESIGN_TOOL_ONLY.sub("", (NODESETS / name).read_text(encoding="utf-8"))


@dataclass(frozen=True)
class StateMachine:
    """A Machinery state machine type: its states' node ids and numbers, read from the nodeset."""

    type_id: ua.NodeId
    states: dict[str, tuple[ua.NodeId, int]]  # BrowseName -> (the state's node id, its StateNumber)


@dataclass(frozen=True)
class Companion:
    """What the gateway uses of the loaded companion specifications."""

    di: int
    machinery: int
    item_state: StateMachine
    operation_mode: StateMachine
    seconds: float  # how long loading them took

    @property
    def machines_folder(self) -> ua.NodeId:
        return nid(MACHINES_FOLDER, self.machinery)

    def ns_of(self, uri: str) -> int:
        return self.di if uri == DI_URI else self.machinery


async def _state_machine(server: Server, type_id: ua.NodeId) -> StateMachine:
    states = {}
    for child in await server.get_node(type_id).get_children(refs=I.HasComponent):
        if (await child.read_type_definition()) not in (nid(I.StateType), nid(I.InitialStateType)):
            continue
        number = await child.get_child("0:StateNumber")
        states[str((await child.read_browse_name()).Name)] = (child.nodeid, int(await number.read_value()))
    return StateMachine(type_id, states)


async def load_companion(server: Server, log: logging.Logger) -> Companion:
    """Import DI, IA and Machinery from their published files (about 0.6 s on an idle machine)."""
    began = time.monotonic()
    importer_log = logging.getLogger("asyncua.common.xmlimporter")
    level = importer_log.level
    importer_log.setLevel(logging.ERROR)  # it warns of every structure it does not generate a class for
    try:
        for name in NODESET_FILES:
            await server.import_xml(xmlstring=published_nodeset(name))
    finally:
        importer_log.setLevel(level)
    di, machinery = await server.get_namespace_index(DI_URI), await server.get_namespace_index(MACHINERY_URI)
    companion = Companion(
        di,
        machinery,
        await _state_machine(server, nid(ITEM_STATE_TYPE, machinery)),
        await _state_machine(server, nid(OPERATION_MODE_TYPE, machinery)),
        time.monotonic() - began,
    )
    log.info("loaded the DI, IA and Machinery nodesets in %.2f s", companion.seconds)
    return companion


def identification(cell_name: str, spec: MachineSpec) -> dict[str, Any]:
    """A machine's Identification from its [[machine]] `identification` table, checked; the three
    mandatory properties have defaults that say they were not configured."""
    given = dict(spec.options.get("identification") or {})
    unknown = set(given) - set(IDENTIFICATION)
    if unknown:
        raise ConfigError(
            f"machine {spec.id}: identification has unknown key(s) {', '.join(sorted(unknown))} "
            f"(known: {', '.join(IDENTIFICATION)})"
        )
    values: dict[str, Any] = {
        "manufacturer": "unknown (set [[machine]] identification.manufacturer)",
        "serial_number": spec.id,
        "product_instance_uri": f"urn:gwc:{cell_name}:machine:{spec.id}",
        "model": spec.kind,
        "component_name": spec.id,
        "asset_id": spec.id,
        "location": cell_name,
        **given,
    }
    for key, value in values.items():
        vtype = IDENTIFICATION[key][2]
        if vtype in (V.UInt16, V.Byte):
            high = 0xFFFF if vtype == V.UInt16 else 0xFF
            if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= high:
                raise ConfigError(f"machine {spec.id}: identification.{key} must be a whole number 0..{high}")
        elif not isinstance(value, str):
            raise ConfigError(f"machine {spec.id}: identification.{key} must be a string")
    return values


@dataclass(frozen=True)
class CellTypes:
    """The cell's own ObjectTypes (namespace urn:gwc:cell), each declaring its data variables."""

    cell: ua.NodeId
    machine: ua.NodeId
    last_run: ua.NodeId
    lot: ua.NodeId
    entity: ua.NodeId
    alarm: ua.NodeId


async def _object_type(
    space: Space, name: str, layout: dict[str, ua.VariantType], parent: int = I.BaseObjectType
) -> ua.NodeId:
    path = f"types/{name}"
    item = ua.AddNodesItem(
        ParentNodeId=nid(parent),
        ReferenceTypeId=nid(I.HasSubtype),
        RequestedNewNodeId=space.nodeid(path),
        BrowseName=ua.QualifiedName(name, space.ns),
        NodeClass=ua.NodeClass.ObjectType,
        NodeAttributes=ua.ObjectTypeAttributes(DisplayName=ua.LocalizedText(name), IsAbstract=False),
    )
    for res in await space.server.iserver.isession.add_nodes([item]):
        res.StatusCode.check()
    node = space.nodeid(path)
    await space.add_variables(node, [(f"{path}/{v}", v, t, I.HasComponent) for v, t in layout.items()])
    await space.add_references(Ref(space.nodeid(f"{path}/{v}"), nid(MANDATORY), I.HasModellingRule) for v in layout)
    return node


async def define_types(space: Space) -> CellTypes:
    """GwcCellType, GwcMachineType, ... under BaseObjectType, in the cell's namespace."""
    return CellTypes(
        cell=await _object_type(space, "GwcCellType", STATUS_LINE),
        machine=await _object_type(space, "GwcMachineType", MACHINE),
        last_run=await _object_type(space, "GwcLastRunType", LAST_RUN),
        lot=await _object_type(space, "GwcLotType", LOT),
        entity=await _object_type(space, "GwcLotEntityType", ENTITY),
        alarm=await _object_type(space, "GwcAlarmType", ALARM),
    )


@dataclass(frozen=True)
class MachineMethod:
    name: str
    callback: MethodCallback
    inputs: Sequence[tuple[str, ua.VariantType, str]]
    outputs: Sequence[tuple[str, ua.VariantType, str]]


async def build_machine(
    space: Space,
    companion: Companion,
    types: CellTypes,
    spec: MachineSpec,
    ident: dict[str, Any],
    methods: Sequence[MachineMethod],
) -> None:
    """One machine as OPC 40001-1 has it, under Objects/Machines (node ids `machines/<id>/...`):

    machine (GwcMachineType)              the cell's variables (status, machine_run_id, ...)
      Identification (MachineIdentificationType, HasAddIn)   Manufacturer, SerialNumber, ...
      MachineryBuildingBlocks (FolderType)  HasAddIn: Identification, MachineryItemState,
                                            MachineryOperationMode
      last_run (GwcLastRunType)             machine_run_id, ack_code, note, ended_at, results
      Start(), Stop(), ...
    """
    path = f"machines/{spec.id}"
    now = datetime.now(UTC)
    node = await space.add_object(companion.machines_folder, path, spec.id, types.machine, I.Organizes)
    await space.add_variables(node, [(f"{path}/{v}", v, t, I.HasComponent) for v, t in MACHINE.items()], now)
    ident_node = await space.add_object(
        node,
        f"{path}/Identification",
        ua.QualifiedName("Identification", companion.di),
        nid(MACHINE_IDENTIFICATION_TYPE, companion.machinery),
        HAS_ADD_IN,
    )
    props = [
        (
            f"{path}/Identification/{IDENTIFICATION[k][0]}",
            ua.QualifiedName(IDENTIFICATION[k][0], companion.ns_of(IDENTIFICATION[k][1])),
            IDENTIFICATION[k][2],
            I.HasProperty,
        )
        for k in ident
    ]
    await space.add_variables(ident_node, props, now)
    for key, value in ident.items():
        await space.set(f"{path}/Identification/{IDENTIFICATION[key][0]}", value, now)
    blocks = await space.add_object(
        node,
        f"{path}/MachineryBuildingBlocks",
        ua.QualifiedName("MachineryBuildingBlocks", companion.machinery),
        I.FolderType,
    )
    for name, machine in (
        ("MachineryItemState", companion.item_state),
        ("MachineryOperationMode", companion.operation_mode),
    ):
        state = await space.add_object(
            blocks, f"{path}/{name}", ua.QualifiedName(name, companion.machinery), machine.type_id, HAS_ADD_IN
        )
        current = f"{path}/{name}/CurrentState"
        await space.add_variables(
            state,
            [(current, ua.QualifiedName("CurrentState", 0), V.LocalizedText, I.HasComponent)],
            now,
            typedef=I.FiniteStateVariableType,
        )
        await space.add_variables(
            space.nodeid(current),
            [
                (f"{current}/Id", ua.QualifiedName("Id", 0), V.NodeId, I.HasProperty),
                (f"{current}/Number", ua.QualifiedName("Number", 0), V.UInt32, I.HasProperty),
            ],
            now,
        )
    await space.add_references([Ref(blocks, ident_node, HAS_ADD_IN)])
    last = await space.add_object(node, f"{path}/last_run", "last_run", types.last_run)
    await space.add_variables(last, [(f"{path}/last_run/{v}", v, t, I.HasComponent) for v, t in LAST_RUN.items()], now)
    for m in methods:
        await space.method(node, f"{path}/{m.name}", m.name, m.callback, m.inputs, m.outputs)


async def set_state(space: Space, path: str, machine: StateMachine, state: str, at: datetime | None = None) -> None:
    """A state machine's CurrentState, its Id and its Number (the nodeset's StateNumber)."""
    state_id, number = machine.states[state]
    await space.set(f"{path}/CurrentState", state, at)
    await space.set(f"{path}/CurrentState/Id", state_id, at)
    await space.set(f"{path}/CurrentState/Number", number, at)
