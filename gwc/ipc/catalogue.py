"""The Conversation Tool: every conversation class and message class the cell speaks, in one place.

A new conversation is one entry here, not new plumbing: the bus validates every message it sends
and receives against these declarations, and the monitor and docs/conversations.md read them.

Field types are written as strings: "str", "int", "float", "bool", "list", "dict"; a trailing
"?" makes the field nullable (it may be absent or null). Every other field is required. A field
added by a later wire version says which after an "@" ("str?@6"): it must be nullable, and a bus
speaking an older version leaves it out (docs/protocol.md, "Versions").
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gwc.errors import MessageError

_TYPES: dict[str, tuple[type, ...]] = {
    "str": (str,),
    "int": (int,),
    "float": (float, int),
    "bool": (bool,),
    "list": (list,),
    "dict": (dict,),
}
MAX_NAME = 200  # characters: ids and names (machine_id, module, op_type, ...); longer is hostile
# Free text: bounded only by the datagram. Every other str field is a name.
TEXT_FIELDS = frozenset({"content", "note", "alarm_text", "text", "payload", "description", "reason", "last_event"})


@dataclass(frozen=True)
class FieldSpec:
    name: str
    type: str
    nullable: bool
    since: int = 0  # the wire version that added it (0: every version has it)


@dataclass(frozen=True)
class MessageClass:
    name: str
    fields: tuple[FieldSpec, ...]
    doc: str = ""
    # Worked out by __post_init__ from `fields`: the names, and one check tuple per field.
    _known: frozenset[str] = field(init=False, repr=False, compare=False)
    _checks: tuple[tuple[str, tuple[type, ...], bool, bool, FieldSpec, int | None], ...] = field(
        init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if {"name", "fields"} & {f.name for f in self.fields}:
            raise ValueError(f"{self.name}: no field may be called name or fields (Message's own attributes)")
        # Worked out once here, not on every check: every message sent and received is checked.
        object.__setattr__(self, "_known", frozenset(f.name for f in self.fields))
        object.__setattr__(
            self,
            "_checks",
            tuple(
                (
                    f.name,
                    _TYPES[f.type],
                    f.type in ("int", "float"),
                    f.nullable,
                    f,
                    (None if f.name in TEXT_FIELDS else MAX_NAME) if f.type == "str" else -1,
                )
                for f in self.fields
            ),
        )
        # The check every message sent and received passes, generated for this class's fields (as
        # dataclasses generates __init__): one expression, no loop over field tuples. It accepts only
        # what is plainly right and leaves everything else to full_check, which says what is wrong.
        object.__setattr__(self, "check", _fast_check(self))

    def check(self, values: dict[str, Any]) -> None:
        """Raise MessageError unless values fit this class exactly (replaced per class by _fast_check,
        which falls back to full_check)."""
        self.full_check(values)

    def full_check(self, values: dict[str, Any]) -> None:
        """Raise MessageError unless values fit this class exactly."""
        known = self._known
        if not known.issuperset(values):
            extra = set(values) - known
            raise MessageError(f"{self.name}: unknown field(s) {', '.join(sorted(extra))}")
        for name, types, numeric, nullable, f, limit in self._checks:
            v: Any = values.get(name)
            if v is None:
                if not nullable:
                    raise MessageError(f"{self.name}: field {name} ({f.type}) is required")
                continue
            if not isinstance(v, types) or (numeric and v.__class__ is bool):
                raise MessageError(f"{self.name}: field {name} must be {f.type}, got {type(v).__name__}")
            if limit != -1 and isinstance(v, str) and ("\0" in v or (limit is not None and len(v) > limit)):
                raise MessageError(f"{self.name}: field {name} holds a NUL or is over {limit} characters")
            if numeric and v != v:  # NaN (the wire refuses it; a message built in Python could hold one)
                raise MessageError(f"{self.name}: field {name} is NaN")


def _fast_check(mc: MessageClass) -> Any:
    """A check function for message class `mc`: returns at once for values of exactly the declared
    types within their limits, calls mc.full_check (which raises saying why, or accepts what only it
    knows, such as a subclass of int) for anything else."""
    terms = ["known.issuperset(values)"]
    for name, _types, _numeric, nullable, f, limit in mc._checks:
        v = "v"
        if f.type == "str":
            ok = f"({v}.__class__ is str and '\\0' not in {v}" + (f" and len({v}) <= {limit})" if limit else ")")
        elif f.type == "float":
            ok = f"({v}.__class__ is int or ({v}.__class__ is float and {v} == {v}))"
        else:
            ok = f"{v}.__class__ is {f.type}"
        got = f"({v} := values.get({name!r}))"
        terms.append(f"({got} is None or {ok})" if nullable else f"({got} is not None and {ok})")
    source = f"def check(values):\n    if {' and '.join(terms)}:\n        return\n    full_check(values)\n"
    scope: dict[str, Any] = {"known": mc._known, "full_check": mc.full_check}
    exec(compile(source, f"<check {mc.name}>", "exec"), scope)
    return scope["check"]


@dataclass(frozen=True)
class ConversationClass:
    name: str
    doc: str
    answered_by: str  # who handles it: a module name, "wc" (the addressed machine), or "any"
    messages: tuple[str, ...]  # the message classes that may appear in it


def _msg(name: str, doc: str = "", **fields: str) -> MessageClass:
    specs = []
    for fname, spec in fields.items():
        ftype, _, since = spec.partition("@")
        nullable = ftype.endswith("?")
        base = ftype.rstrip("?")
        if base not in _TYPES:
            raise ValueError(f"catalogue: {name}.{fname} has unknown type {spec}")
        if since and not (since.isdigit() and nullable):
            raise ValueError(f"catalogue: {name}.{fname}: a field added by a version must be nullable (type?@N)")
        specs.append(FieldSpec(fname, base, nullable, int(since or 0)))
    return MessageClass(name, tuple(specs), doc)


@functools.cache
def fields_after(version: int) -> Mapping[str, frozenset[str]]:
    """Message class -> its fields that wire versions after `version` added: what a bus speaking
    `version` leaves out of what it sends (gwc.ipc.wire.Origin.omit). Empty for this build's own."""
    return {
        m.name: frozenset(f.name for f in m.fields if f.since > version)
        for m in MESSAGE_CLASSES.values()
        if any(f.since > version for f in m.fields)
    }


ACK = {"ack_code": "str", "note": "str?"}

MESSAGE_CLASSES: dict[str, MessageClass] = {
    m.name: m
    for m in (
        # --- module lifecycle (every server, MSCHED, every WC) ---
        _msg("Startup_Request", "ask a module (or a machine's WC) to start", module="str"),
        _msg("Startup_Ack", "startup accepted (ACK_OK) or refused (Notnow, Start_Fail)", **ACK),
        _msg("Startup_Complete", "the module is up and listening", **ACK),
        _msg("Shutdown_Request", "ask a module to shut down", module="str"),
        _msg("Shutdown_Ack", **ACK),
        _msg("Shutdown_Complete", **ACK),
        _msg("ME_Ready", "the machine is homed, Idle and accepts all operations", machine_id="str", **ACK),
        _msg("ME_Stopped", "the machine is Shutdown", machine_id="str", **ACK),
        # --- MSCHED ---
        _msg(
            "Machine_Request",
            "first of 1+N: N Machine_Entry follow; requests of an entity with the same alt_group are "
            "alternatives of one need: once one is bound, a later one is refused REQ_CANCEL",
            entity_id="int",
            op_type="str",
            num_machines="int",
            priority="int?",
            alt_group="str?",
        ),
        _msg("Machine_Entry", "one machine of a request (AND)", machine_id="str"),
        _msg("Machine_Req_Ack", "request queued", request_key="int?", **ACK),
        _msg(
            "Machine_Req_Comp",
            "the request ended: ACK_OK (bound; N Reserved_Machine follow), NO_MACHINE, REQ_CANCEL",
            entity_id="int",
            machine_run_id="int?",
            request_key="int?",
            num_machines="int",
            **ACK,
        ),
        _msg("Reserved_Machine", "one machine bound to the entity", machine_id="str"),
        _msg("Request_Comp_Ack", "the entity got its Machine_Req_Comp", entity_id="int", **ACK),
        _msg(
            "Cancel_Request",
            "cancel one request (or all of an entity's when request_key is null)",
            request_key="int?",
            entity_id="int?",
            by="str?",
        ),
        _msg("Cancel_Req_Ack", "ACK_OK or REQ_KEY_U (nothing to cancel)", cancelled="int?", **ACK),
        _msg(
            "Update_ME_Status",
            "a machine's status changed (broadcast by the Machine Server)",
            machine_id="str",
            status="str",
            previous="str?",
            machine_run_id="int?",
            note="str?",
        ),
        _msg(
            "Module_Died",
            "a module's process died (broadcast by its host's agent the moment it learns of it)",
            module="str",
            host="str",
            pid="int?",
            how="str",
            state="str",
            restarts="int",
            restart_in="float?",
        ),
        _msg(
            "Chg_Accept_Type",
            "set the op types a machine accepts (null/empty = none, ['*'] = all)",
            machine_id="str",
            op_types="list",
        ),
        _msg("Chg_Accept_Type_Ack", **ACK),
        _msg(
            "Unreserve_Me",
            "free machines reserved by an entity (all of them if machine_id is null)",
            entity_id="int",
            machine_id="str?",
            by="str?",
        ),
        _msg("Unreserve_Me_Ack", freed="int?", **ACK),
        # --- WC (addressed to one machine) ---
        _msg(
            "Setup_Run",
            "download a recipe and set the machine up for a run (no recipe_id: the machine's for op_type; "
            "start: and start the run once set up, as a Start_Run would; sheet: the run's own lines after "
            "the recipe, {workpiece, tool, offsets}: docs/quality.md)",
            machine_id="str",
            recipe_id="str?",
            op_type="str",
            machine_run_id="int",
            entity_id="int?",
            start="bool?",
            sheet="dict?",
        ),
        _msg(
            "Setup_Run_Ack", "recipe_id: the recipe set up (with start: and the run started)", recipe_id="str?", **ACK
        ),
        _msg("Start_Run", "start the run that was set up", machine_id="str", machine_run_id="int"),
        _msg("Start_Run_Ack", **ACK),
        _msg(
            "Run_Complete",
            "a run ended; results are in MACHINE_RUN_RESULT, and in results (param -> value) when they are small",
            machine_id="str",
            machine_run_id="int?",
            results="dict?",
            **ACK,
        ),
        _msg("Download_Me", "send a recipe to the machine", machine_id="str", recipe_id="str"),
        _msg("Download_Ack", **ACK),
        _msg("Upload_Me", "bring the machine's recipe back to the cell", machine_id="str", recipe_id="str"),
        _msg("Upload_Ack", version="int?", **ACK),
        # --- alarms (Cell Alarm Server) ---
        _msg("Alarm_Send", "raise an alarm", alarm_id="str", alarm_text="str?", machine_id="str?", raised_by="str"),
        _msg("Alarm_Ack", alarm_no="int?", known="bool?", **ACK),
        _msg(
            "Alarm_Clear",
            "an alarm was cleared by the operator (broadcast)",
            alarm_no="int",
            alarm_id="str?",
            machine_id="str?",
            cleared_by="str",
        ),
        _msg("Alarm_Clear_Request", "the operator clears an alarm", alarm_no="int", cleared_by="str"),
        _msg("Alarm_Clear_Ack", **ACK),
        _msg(
            "Alarm_Describe",
            "the operator describes an alarm: its text, severity and what the CAS does for it "
            "(actions: shutdown, page); null fields are left as they are",
            alarm_id="str",
            alarm_text="str?",
            severity="str?",
            actions="list?",
            by="str?",
        ),
        # --- Machine Server ---
        _msg(
            "Change_Status",
            "set a machine's status",
            machine_id="str",
            status="str",
            recipe_id="str?",
            machine_run_id="int?",
            note="str?",
            expect="list?",
        ),
        _msg("Change_Status_Ack", status="str?", previous="str?", **ACK),
        _msg("Get_Status", machine_id="str"),
        _msg("Status_Reply", machine_id="str", status="str?", recipe_id="str?", machine_run_id="int?", **ACK),
        _msg(
            "Maint_Done", "the operator maintained a machine: its run count starts again", machine_id="str", by="str?"
        ),
        _msg("Maint_Done_Ack", "runs = the count before the reset", runs="int?", **ACK),
        _msg(
            "Scrap_Report",
            "a lot entity scrapped parts a machine's run made (its verdict): the machine's scrap count",
            entity_id="int",
            machine_id="str",
            machine_run_id="int",
            parts="int",
            reason="str?",
        ),
        _msg(
            "Downtime_Reason",
            "the operator gives a downtime event its reason (one of cell.toml's reason tree): the event "
            "event_id, or the open one of machine_id",
            event_id="int?",
            machine_id="str?",
            reason="str",
            by="str?",
        ),
        _msg("Downtime_Reason_Ack", "event_id and e10_state as recorded", event_id="int?", e10_state="str?", **ACK),
        # --- Lot Server ---
        _msg(
            "Lot_Action",
            "an operator action on an entity done elsewhere (a cancel, told MSCHED): kept in its history",
            entity_id="int",
            action="str",
            by="str",
            note="str?",
        ),
        _msg("Lot_Action_Ack", lot_id="int?", **ACK),
        _msg(
            "Create_Lot_Entity",
            "request_id: the asker's id for this creation; a repeat gets what the first made",
            lot_type="str?",
            lot_id="int?",
            product_id="str",
            quantity="int",
            priority="int?",
            owner="str?",
            result_params="list?",
            script_id="str?",
            work_order_id="int?",
            request_id="str?",
        ),
        _msg("Create_Lot_Ack", lot_id="int?", entity_ids="list?", **ACK),
        _msg(
            "Entity_Request",
            "an entity asks (import, export, completed, failed, state)",
            entity_id="int",
            action="str",
            reason="str?",
            script_pid="int?",
        ),
        _msg(
            "Entity_Ack",
            "to an attach, also the entity's lot and its lot script (the lot's own, else its product's)",
            lot_id="int?",
            state="str?",
            product_id="str?",
            priority="int?",
            work_order_id="int?",
            script_id="str?",
            script_path="str?",
            **ACK,
        ),
        _msg(
            "Lot_Decision",
            "the operator imports, exports or releases (retry, reroute, fail) an entity",
            entity_id="int",
            action="str",
            by="str?",
        ),
        _msg("Lot_Decision_Ack", lot_id="int?", **ACK),
        _msg(
            "Lot_Moved",
            "broadcast: an entity was imported, exported or released",
            entity_id="int",
            action="str",
            lot_id="int?",
        ),
        _msg("Divide_Merge", entity_id="int", action="str", other_entity_id="int?", quantity="int?"),
        _msg("Divide_Merge_Ack", entity_ids="list?", **ACK),
        # --- Equipment Recipe Server ---
        _msg(
            "Recipe_Fetch", "ask for the approved version of a recipe for a machine", recipe_id="str", machine_id="str?"
        ),
        _msg("Recipe_Reply", recipe_id="str?", version="int?", checksum="str?", content="str?", **ACK),
        _msg(
            "Recipe_Store",
            "store content as a new version",
            recipe_id="str",
            content="str",
            by="str?",
            description="str?",
        ),
        _msg("Recipe_Store_Ack", version="int?", checksum="str?", **ACK),
        _msg(
            "Recipe_Approve",
            "approve a version (null: the latest); an edited library file becomes a new version",
            recipe_id="str",
            version="int?",
            by="str?",
        ),
        # --- Status Line Server ---
        _msg("Status_Line_Get"),
        _msg(
            "Status_Line",
            "the status line; ack_code and note only on a refusal",
            text="str",
            imports="int?",
            exports="int?",
            alarms="int?",
            last_event="str?",
            ack_code="str?",
            note="str?",
        ),
        _msg("Cell_Event", "a cell event worth the status line", text="str", source="str?"),
        # --- generic ---
        _msg("Ack", **ACK),
        _msg("Ping", "bus test traffic", n="int", payload="str?"),
        _msg(
            "Pong",
            "the Ping's n; ack_code and note only on a refusal",
            n="int",
            payload="str?",
            ack_code="str?",
            note="str?",
        ),
    )
}


def _conv(name: str, doc: str, answered_by: str, *messages: str) -> ConversationClass:
    for m in messages:
        if m not in MESSAGE_CLASSES:
            raise ValueError(f"catalogue: conversation {name} names unknown message {m}")
    return ConversationClass(name, doc, answered_by, messages)


_LIFE_START = ("Startup_Request", "Startup_Ack", "Startup_Complete")
_LIFE_STOP = ("Shutdown_Request", "Shutdown_Ack", "Shutdown_Complete")

CONVERSATION_CLASSES: dict[str, ConversationClass] = {
    c.name: c
    for c in (
        _conv("STARTUP", "start a server module", "any", *_LIFE_START),
        _conv("SHUTDOWN", "shut a server module down", "any", *_LIFE_STOP),
        _conv("ME_START", "start a machine (its WC and ME)", "wc", *_LIFE_START, "ME_Ready"),
        _conv("ME_SHUT", "shut a machine down", "wc", *_LIFE_STOP, "ME_Stopped"),
        _conv(
            "MACH_REQ",
            "an entity asks MSCHED for machines",
            "msched",
            "Machine_Request",
            "Machine_Entry",
            "Machine_Req_Ack",
            "Machine_Req_Comp",
            "Reserved_Machine",
            "Request_Comp_Ack",
        ),
        _conv("CANCEL_RE", "cancel a machine request", "msched", "Cancel_Request", "Cancel_Req_Ack"),
        _conv("UPD_ME_ST", "a machine's status changed (broadcast)", "any", "Update_ME_Status"),
        _conv("MOD_DIED", "a module's process died (broadcast by the agent)", "any", "Module_Died"),
        _conv("ACC_TYP_C", "change the op types a machine accepts", "msched", "Chg_Accept_Type", "Chg_Accept_Type_Ack"),
        _conv("UNRESERVE", "free reserved machines", "msched", "Unreserve_Me", "Unreserve_Me_Ack"),
        _conv("SETUP_RUN", "set a machine up for a run", "wc", "Setup_Run", "Setup_Run_Ack"),
        _conv("START_RUN", "start a set-up run", "wc", "Start_Run", "Start_Run_Ack"),
        _conv("RUN_COMPL", "a run completed (broadcast by the WC)", "any", "Run_Complete"),
        _conv("DNLD_ME", "download a recipe to a machine", "wc", "Download_Me", "Download_Ack"),
        _conv("UPLD_ME", "upload a recipe from a machine", "wc", "Upload_Me", "Upload_Ack"),
        _conv("ALARM_SEND", "raise an alarm", "cas", "Alarm_Send", "Alarm_Ack"),
        _conv("ALARM_CLE", "an alarm was cleared (broadcast by CAS)", "any", "Alarm_Clear"),
        _conv("ALARM_CLR_REQ", "the operator clears an alarm", "cas", "Alarm_Clear_Request", "Alarm_Clear_Ack"),
        _conv("ALARM_DESC", "describe an alarm and its actions", "cas", "Alarm_Describe", "Alarm_Clear_Ack"),
        _conv("CHG_STATUS", "change a machine's status", "ms", "Change_Status", "Change_Status_Ack"),
        _conv("GET_STATUS", "read a machine's status", "ms", "Get_Status", "Status_Reply"),
        _conv("MAINT_DONE", "a machine was maintained", "ms", "Maint_Done", "Maint_Done_Ack"),
        _conv("SCRAP_RPT", "a lot scrapped parts of a machine's run", "ms", "Scrap_Report", "Ack"),
        _conv(
            "DOWNTIME_RSN", "the operator gives a downtime its reason", "ms", "Downtime_Reason", "Downtime_Reason_Ack"
        ),
        _conv("LOT_ACTION", "record an operator action on an entity", "ls", "Lot_Action", "Lot_Action_Ack"),
        _conv("CREATE_LOT", "create a lot entity", "ls", "Create_Lot_Entity", "Create_Lot_Ack"),
        _conv(
            "ENTITY_REQ",
            "an entity asks the Lot Server for import, export, completion",
            "ls",
            "Entity_Request",
            "Entity_Ack",
        ),
        _conv("IMPORT_LOT", "the operator imports an entity", "ls", "Lot_Decision", "Lot_Decision_Ack"),
        _conv("EXPORT_LOT", "the operator exports an entity", "ls", "Lot_Decision", "Lot_Decision_Ack"),
        _conv(
            "RELEASE_LOT",
            "the operator releases a held entity: retry, reroute or fail",
            "ls",
            "Lot_Decision",
            "Lot_Decision_Ack",
        ),
        _conv(
            "LOT_MOVED",
            "an entity was imported or exported (broadcast; its own lot script told addressed)",
            "any",
            "Lot_Moved",
        ),
        _conv("DIV_MERGE", "divide or merge entities", "ls", "Divide_Merge", "Divide_Merge_Ack"),
        _conv("RECIPE_GET", "fetch an approved recipe", "ers", "Recipe_Fetch", "Recipe_Reply"),
        _conv("RECIPE_PUT", "store a recipe version", "ers", "Recipe_Store", "Recipe_Store_Ack"),
        _conv("RECIPE_APPR", "approve a recipe version", "ers", "Recipe_Approve", "Recipe_Store_Ack"),
        _conv("STATUS_LN", "read the status line", "sls", "Status_Line_Get", "Status_Line"),
        _conv("CELL_EVENT", "a cell event for the status line (broadcast)", "any", "Cell_Event"),
        _conv("PING", "bus test and benchmark traffic", "any", "Ping", "Pong"),
    )
}


# How each conversation with more than one answer goes: who sends what, and which message ends it
# (docs/conversations.md prints a line per class; a class of one or two messages is described by
# sequence() alone). "->" is the other side's turn; a refusal is always the class's ack message
# with a code other than ACK_OK, and it ends the conversation.
SEQUENCES = {
    "STARTUP": "Startup_Request -> Startup_Ack (Notnow ends it: already started; ACK_OK: the start begins) "
    "-> Startup_Complete, which ends it (its ack_code says how the start went)",
    "SHUTDOWN": "Shutdown_Request -> Shutdown_Ack (Notnow ends it: not started; ACK_OK: the stop begins) "
    "-> Shutdown_Complete, which ends it",
    "ME_START": "Startup_Request (module = the WC's bus name, wc:<machine>) -> Startup_Ack (Notnow ends it; "
    "ACK_OK: the ME homes, which may wait for the operator) -> ME_Ready, which ends it (ACK_OK: Idle; else "
    "Start_Fail, REQ_CANCEL when a stop came first). Startup_Complete is not used in it",
    "ME_SHUT": "Shutdown_Request (module = wc:<machine>) -> Shutdown_Ack (Notnow ends it) -> ME_Stopped, "
    "which ends it. Shutdown_Complete is not used in it",
    "MACH_REQ": "Machine_Request + N x Machine_Entry (one batch) -> Machine_Req_Ack (a code other than ACK_OK "
    "ends it; ACK_OK carries the request_key) -> later, Machine_Req_Comp (+ N x Reserved_Machine when "
    "ACK_OK: bound; else NO_MACHINE or REQ_CANCEL) -> Request_Comp_Ack from the asker, which ends it",
}


def sequence(cls: str) -> str:
    """How a conversation of class `cls` goes, in one line (docs/conversations.md)."""
    if cls in SEQUENCES:
        return SEQUENCES[cls]
    messages = CONVERSATION_CLASSES[cls].messages
    if len(messages) == 1:
        return f"{messages[0]}, broadcast (or addressed to one module); nobody answers: the opener ends it"
    return f"{messages[0]} -> {messages[1]}, which ends it (ACK_OK or a refusal)"


# The conversation classes a lot entity starts or answers: all that receivers accept under the lot
# key (docs/security.md). Everything else a lot script sends is refused Not_Auth. The server of each
# checks that the asker lot:E holds what it asks about (Listing 1's calls, docs/lot-scripts.md): a WC
# downloads to and uploads from a machine reserved to E; the ERS stores a proposed version only of a
# recipe for a machine reserved to E, unapproved; the Lot Server makes a lot created by E E's child;
# the Machine Server takes E's scrap report in E's name only; the Lot Server lets E divide itself and
# merge its own children into itself; the Cell Alarm Server takes quality's alarms (SPC_RULE, TOOL_CHANGE)
# from E in E's name only.
LOT_CLASSES = frozenset(
    {
        "MACH_REQ",
        "CANCEL_RE",
        "UNRESERVE",
        "SETUP_RUN",
        "START_RUN",
        "ENTITY_REQ",
        "DNLD_ME",
        "UPLD_ME",
        "RECIPE_PUT",
        "CREATE_LOT",
        "SCRAP_RPT",
        "DIV_MERGE",
        "ALARM_SEND",
    }
)

# Classes whose broadcasts are about one subject, named by a field of their first message: a module may hear
# them about some subjects only (a lot, about its own machines). The bus puts the subject in the header, where
# the kernel filter reads it (docs/protocol.md, "Subjects").
SUBJECT_FIELDS: dict[str, str] = {"UPD_ME_ST": "machine_id", "RUN_COMPL": "machine_id"}


class Message:
    """One message of a conversation: its class name and its field values (validated).

    Its fields are its instance dict, so `msg.entity_id` is a plain attribute read: on Python 3.11 a
    read through __getattr__ first raises and formats an AttributeError, about 1 us, several times a
    message on the bus's hot path. A value: not to be changed once made.
    """

    __slots__ = ("__dict__", "name")

    def __init__(self, name: str, fields: dict[str, Any]) -> None:
        self.name = name
        self.__dict__ = fields

    @property
    def fields(self) -> dict[str, Any]:
        return self.__dict__

    def __getattr__(self, item: str) -> Any:
        # Only for names that are not fields present: declared-but-absent nullable fields read as None.
        if not item.startswith("__"):
            mc = MESSAGE_CLASSES.get(self.name)
            if mc and item in mc._known:
                return None
        raise AttributeError(f"{self.name} has no field {item}")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Message) and other.name == self.name and other.__dict__ == self.__dict__

    # A value that holds a dict: unhashable, as the dataclass it was.
    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Message(name={self.name!r}, fields={self.__dict__!r})"


def message(name: str, **fields: Any) -> Message:
    """Build a message, checked against the catalogue (None values are left out)."""
    mc = MESSAGE_CLASSES.get(name)
    if mc is None:
        raise MessageError(f"unknown message class {name!r}")
    values = {k: v for k, v in fields.items() if v is not None}
    mc.check(values)
    return Message(mc.name, values)  # the catalogue's own str, not a Msg member: hashed on every send


# (conversation class, message class) -> the message class: one lookup for every message received.
MEMBERS = _MEMBERS = {(c.name, m): MESSAGE_CLASSES[m] for c in CONVERSATION_CLASSES.values() for m in c.messages}


def check(cls: str, msg: str, fields: dict[str, Any]) -> Message:
    """Validate a received (cls, msg, fields) triple; raise MessageError on any mismatch."""
    mc = _MEMBERS.get((cls, msg))
    if mc is None:
        if cls not in CONVERSATION_CLASSES:
            raise MessageError(f"unknown conversation class {cls!r}")
        raise MessageError(f"message {msg!r} does not belong to conversation {cls}")
    mc.check(fields)
    return Message(msg, fields)


def refusal(cls: str, ack_code: str, note: str, opener: Mapping[str, Any] | None = None) -> Message | None:
    """The answer that refuses a conversation of class `cls` with ack_code (docs/protocol.md, "Refusals"):
    its first answer message that has an ack_code field, with the note (cut to 500 characters), and
    every other field it requires taken from the opener's field of the same name (Status_Reply's
    machine_id, Pong's n) or, for a `text`, the code and the note. None if the class has no answer (a
    broadcast) or the opener lacks what the answer requires."""
    for name in CONVERSATION_CLASSES[cls].messages[1:]:
        mc = MESSAGE_CLASSES[name]
        if "ack_code" not in mc._known:
            continue
        values: dict[str, Any] = {"ack_code": ack_code}
        if "note" in mc._known:
            values["note"] = note[:500]
        for f in mc.fields:
            if f.nullable or f.name in values:
                continue
            if opener is not None and opener.get(f.name) is not None:
                values[f.name] = opener[f.name]
            elif f.name == "text":
                values["text"] = f"{ack_code}: {note}"[:500]
        try:
            mc.check(values)
        except MessageError:
            return None
        return Message(name, values)
    return None
