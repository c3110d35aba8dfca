"""`gwc monitor`: the Conversation Monitor (CMON). Every conversation on the bus, live and decoded.

The monitor joins the cell's multicast group but never speaks: it sends no hello, no ack, so the
modules do not count it and it changes nothing it watches. It checks every datagram with the cell's
key as a module would (gwc/ipc/auth.py), decodes what is authentic with the same wire module as the
bus, shows each message once (retransmissions and duplicates are recognised by (sender,
incarnation, seq)), and notes which modules acknowledged it. `--record FILE` appends one JSON object
per line for each message shown, for later study or for tests.

Without the key (`--no-key`, or none readable) it decodes nothing: it shows only that traffic it
cannot authenticate exists, how much each second. With it, refused datagrams are counted the same way.
"""

from __future__ import annotations

import collections
import json
import logging
import select
import time
from collections import OrderedDict
from collections.abc import Callable
from datetime import datetime
from typing import Any, TextIO

import click

from gwc.config import BusConfig
from gwc.errors import BusError, GwcError, MessageError
from gwc.hi import context
from gwc.ipc import catalogue, keys, wire
from gwc.ipc.auth import Guard
from gwc.ipc.conversation import initiator
from gwc.ipc.transport import open_socket
from gwc.log import escape
from gwc.retry import Deadline

SEEN_MAX = 100_000


def record_of(env: wire.Envelope, bus: str, now: float) -> dict[str, Any]:
    """What the monitor shows and records of one msg datagram."""
    return {
        "time": datetime.fromtimestamp(now).isoformat(" ", "milliseconds"),
        "bus": bus,
        "class": env.cls,
        "conv": env.conv,
        "initiator": initiator(env.conv),
        "from": env.src,
        "to": env.to,
        "message": env.msg,
        "idx": env.idx,
        "more": env.more,
        "fields": env.fields,
        "ack_code": env.fields.get("ack_code"),
        "seq": env.seq,
        "wire": env.version,  # the version it was encoded in: the lowest the cell speaks now
    }


def matches(
    rec: dict[str, Any],
    classes: tuple[str, ...],
    modules: tuple[str, ...],
    machines: tuple[str, ...],
    machine_convs: set[str] | None = None,
) -> bool:
    """The filters: any of the classes, any of the modules (sender, addressee or initiator), any machine.

    A message about a machine (its machine_id, or its WC as a party) matches, and so does every later
    message of a conversation that did (pass the same `machine_convs` set each time).
    """
    if classes and rec["class"] not in classes:
        return False
    if modules and not {rec["from"], rec["to"], rec["initiator"]} & set(modules):
        return False
    if machines:
        involved = {rec["fields"].get("machine_id")} | {
            m[3:] for m in (rec["from"], rec["to"], rec["initiator"]) if m and m.startswith("wc:")
        }
        if involved & set(machines):
            if machine_convs is not None:
                machine_convs.add(rec["conv"])
        elif machine_convs is None or rec["conv"] not in machine_convs:
            return False
    return True


def line_of(rec: dict[str, Any]) -> str:
    fields = " ".join(f"{k}={v}" for k, v in rec["fields"].items() if k != "ack_code")
    code = f" [{rec['ack_code']}]" if rec["ack_code"] else ""
    more = f" (+{rec['more']})" if rec["more"] else ""
    speaks = f"@v{rec['speaks']}" if rec.get("speaks") else ""  # the highest wire version its sender speaks
    return (
        f"{rec['time'][11:]} {rec['bus']} {rec['class']:<13} {rec['conv']:<28} {rec['from']}{speaks} -> "
        f"{rec['to'] or '*'}  {rec['message']}{more}{code} {fields}"
    ).rstrip()


def watch(
    cfg: BusConfig,
    emit: Callable[[dict[str, Any]], None],
    stop: Callable[[], bool],
    show_acks: bool = False,
    ready: Callable[[], None] = lambda: None,
    keyed: bool = True,
    show_members: bool = False,
) -> dict[str, int]:
    """Listen to the group until stop() says so; emit each new msg once (and acks, if asked).

    Without the key (keyed False) nothing is decoded: every second with traffic emits how many
    datagrams came that could not be authenticated."""
    guard = Guard(cfg, "monitor", logging.getLogger("gwc.monitor"), collections.Counter()) if keyed else None
    sock = open_socket(cfg)
    try:  # beats: every module's hello each heartbeat, which says the wire version it speaks
        beat_sock = open_socket(cfg, cfg.port + 1)
    except BaseException:
        sock.close()
        raise
    versions = Versions(cfg.name, emit if show_members else None)
    ready()
    seen: OrderedDict[tuple[str, int, int], dict[str, Any]] = OrderedDict()
    counts = {"datagrams": 0, "messages": 0, "malformed": 0, "unauthenticated": 0}
    second, unauthenticated = time.monotonic() + 1.0, 0
    try:
        while not stop():
            if time.monotonic() >= second:
                if unauthenticated:
                    now = datetime.now().isoformat(" ", "milliseconds")
                    emit({"time": now, "bus": cfg.name, "unauthenticated": unauthenticated, "keyed": keyed})
                second, unauthenticated = time.monotonic() + 1.0, 0
            readable, _, _ = select.select([sock, beat_sock], [], [], 0.1)
            if not readable:
                continue
            if beat_sock in readable:
                versions.read_beats(beat_sock, guard)
                if sock not in readable:
                    continue
            try:
                data, source = sock.recvfrom(65536)
            except BlockingIOError:
                continue
            counts["datagrams"] += 1
            opened = guard.open(data, False, source) if guard is not None else None
            if opened is None:
                counts["unauthenticated"] += 1
                unauthenticated += 1
                continue
            try:
                env = wire.decode(opened[0])
            except MessageError as e:
                counts["malformed"] += 1
                emit({"time": datetime.now().isoformat(" ", "milliseconds"), "bus": cfg.name, "malformed": str(e)})
                continue
            if env.kind == "ack" or env.acks:
                for seq in env.acks:
                    rec = seen.get((env.to or "", env.to_inc, seq))
                    if rec is not None and env.src not in rec["acked_by"]:
                        rec["acked_by"].append(env.src)
                        if show_acks:
                            emit(
                                {
                                    "time": datetime.now().isoformat(" ", "milliseconds"),
                                    "bus": cfg.name,
                                    "ack": seq,
                                    "of": rec["message"],
                                    "conv": rec["conv"],
                                    "by": env.src,
                                }
                            )
            if env.kind == "hello":
                versions.heard(env)
            if env.kind != "msg":
                continue
            key = (env.src, env.inc, env.seq)
            if key in seen:
                continue  # a retransmission or a duplicate: shown once
            rec = record_of(env, cfg.name, time.time())
            rec["speaks"] = versions.speaks.get(env.src)
            rec["acked_by"] = []
            seen[key] = rec
            while len(seen) > SEEN_MAX:
                seen.popitem(last=False)
            counts["messages"] += 1
            emit(rec)
    finally:
        sock.close()
        beat_sock.close()
    return counts


class Versions:
    """The wire version each module speaks, from its hellos (on the bus port) and beats (the beat port):
    what the monitor shows beside each message's sender, and with --members as each one changes."""

    def __init__(self, bus: str, emit: Callable[[dict[str, Any]], None] | None) -> None:
        self.bus = bus
        self.emit = emit
        self.speaks: dict[str, int] = {}  # module -> the highest version it speaks
        self.sends: dict[str, int] = {}  # module -> the version its datagrams are in now

    def read_beats(self, sock: Any, guard: Guard | None) -> None:
        while True:
            try:
                data, source = sock.recvfrom(65536)
            except BlockingIOError:
                return
            opened = guard.open(data, True, source) if guard is not None else None
            if opened is None:
                continue
            try:
                env = wire.decode(opened[0])
            except MessageError:
                continue
            if env.kind == "hello":
                self.heard(env)

    def heard(self, env: wire.Envelope) -> None:
        speaks = env.fields.get(wire.SPEAKS)
        speaks = speaks if type(speaks) is int else env.version
        if env.query:  # a sign-on query is in the oldest version its sender speaks: not what it speaks now
            self.speaks[env.src] = speaks
            # A new incarnation (a module restarted, perhaps of another build): what it sends in is known
            # from its next hello, which is shown even when it speaks and sends as the one before did.
            self.sends.pop(env.src, None)
            return
        if self.speaks.get(env.src) == speaks and self.sends.get(env.src) == env.version:
            return
        self.speaks[env.src], self.sends[env.src] = speaks, env.version
        if self.emit is not None:
            now = datetime.now().isoformat(" ", "milliseconds")
            self.emit({"time": now, "bus": self.bus, "member": env.src, "speaks": speaks, "wire": env.version})


def render_catalogue() -> str:
    """docs/conversations.md, generated from the catalogue so that the two cannot drift apart."""
    out = [
        "# Conversations",
        "",
        "Generated from `gwc/ipc/catalogue.py` by `gwc monitor --catalogue` (a test checks this file matches):",
        "edit the catalogue, then regenerate this file; never edit it by hand.",
        "",
        "A conversation is opened by its first listed message; the others may follow in it, in either direction.",
        "Field types: `str`, `int`, `float`, `bool`, `list`, `dict`; `?` marks a nullable field (absent or null).",
        "",
        "## Conversation classes",
        "",
        "*Answered by* names the module that serves the class: a bus name (`msched`, `ms`, `ls`, `cas`, `ers`,",
        "`sls`), `wc` for the WC of the machine the opener is addressed to (bus name `wc:<machine id>`), or",
        "`any` for a class every module may open or hear (a broadcast, or a lifecycle class each module serves",
        "for itself). An opener addressed to a module that does not serve its class now is answered `Notnow`",
        "(docs/protocol.md, *Refusals*).",
        "",
        "| Class | Answered by | Messages | What it is for |",
        "|---|---|---|---|",
    ]
    for c in catalogue.CONVERSATION_CLASSES.values():
        out.append(f"| `{c.name}` | {c.answered_by} | {', '.join(c.messages)} | {c.doc} |")
    out += [
        "",
        "## Sequences",
        "",
        "Each class's turns: `->` is the other side's; the message named last ends the conversation.",
        "",
    ]
    out += [f"* `{c}`: {catalogue.sequence(c)}." for c in catalogue.CONVERSATION_CLASSES]
    lot = ", ".join(f"`{c}`" for c in catalogue.CONVERSATION_CLASSES if c in catalogue.LOT_CLASSES)
    out += [
        "",
        f"Under the lot key (lot scripts, docs/security.md) receivers accept only {lot};",
        "anything else a lot script sends is refused `Not_Auth`.",
    ]
    out += ["", "## Message classes", "", "| Message | Fields | What it says |", "|---|---|---|"]
    for m in catalogue.MESSAGE_CLASSES.values():
        fields = (
            ", ".join(
                f"`{f.name}: {f.type}{'?' if f.nullable else ''}{f'@{f.since}' if f.since else ''}`" for f in m.fields
            )
            or "(none)"
        )
        out.append(f"| `{m.name}` | {fields} | {m.doc} |")
    from gwc.ipc.codes import AckCode

    out += [
        "",
        "## Ack codes",
        "",
        "Carried in `ack_code` by every acknowledgement.",
        "",
        "| Code | Python |",
        "|---|---|",
    ]
    out += [f"| `{a.value}` | `AckCode.{a.name}` |" for a in AckCode]
    return "\n".join(out) + "\n"


@click.command("monitor")
@click.option("--class", "classes", multiple=True, help="Only these conversation classes (repeatable).")
@click.option("--module", "modules", multiple=True, help="Only conversations this module sends, receives or opened.")
@click.option(
    "--machine",
    "machines",
    multiple=True,
    help="Only conversations about this machine (from the first message naming it or its WC).",
)
@click.option("--record", "record", type=click.File("a"), help="Also append each message as a JSON line to FILE.")
@click.option("--acks", "show_acks", is_flag=True, help="Also show each transport acknowledgement as it comes.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON lines instead of text.")
@click.option("--count", type=int, help="Stop after this many messages.")
@click.option("--duration", type=float, help="Stop after this many seconds.")
@click.option("--no-key", "no_key", is_flag=True, help="Do not load the cell key: only count the traffic.")
@click.option(
    "--members",
    "show_members",
    is_flag=True,
    help="Also show each module's wire version (what it speaks, what it sends in) as it is heard or changes.",
)
@click.option(
    "--catalogue", "show_catalogue", is_flag=True, help="Print the conversation catalogue (markdown) and exit."
)
def monitor(
    classes: tuple[str, ...],
    modules: tuple[str, ...],
    machines: tuple[str, ...],
    record: TextIO | None,
    show_acks: bool,
    as_json: bool,
    count: int | None,
    duration: float | None,
    no_key: bool,
    show_members: bool,
    show_catalogue: bool,
) -> None:
    """Watch every conversation on the cell bus, live and decoded (the Conversation Monitor)."""
    if show_catalogue:
        click.echo(render_catalogue(), nl=False)
        return
    unknown = set(classes) - set(catalogue.CONVERSATION_CLASSES)
    if unknown:
        raise GwcError(f"unknown conversation class(es): {', '.join(sorted(unknown))}")
    cfg, _ = context()
    deadline = Deadline(duration)  # None: never
    shown = 0
    machine_convs: set[str] = set()

    def emit(rec: dict[str, Any]) -> None:
        nonlocal shown
        if "message" in rec and not matches(rec, classes, modules, machines, machine_convs):
            return
        if "message" not in rec and (classes or modules or machines) and not (show_members and "member" in rec):
            return
        text = json.dumps(rec, default=str)
        if record is not None:
            record.write(text + "\n")
            record.flush()
        if as_json:  # JSON escapes every control character itself
            click.echo(text)
        elif "message" in rec:  # what came off the wire (names, ids, fields) never reaches the terminal raw
            click.echo(escape(line_of(rec)))
        elif "ack" in rec:
            click.echo(escape(f"{rec['time'][11:]} {rec['bus']}   ack {rec['of']} in {rec['conv']} by {rec['by']}"))
        elif "member" in rec:
            click.echo(
                escape(
                    f"{rec['time'][11:]} {rec['bus']}   {rec['member']} speaks wire version {rec['speaks']}"
                    f" (sends {rec['wire']})"
                )
            )
        elif "unauthenticated" in rec:
            why = "refused: not authentic, not fresh or another cell's" if rec["keyed"] else "no key: not decoded"
            click.echo(f"{rec['time'][11:]} {rec['bus']}   {rec['unauthenticated']} datagram(s) ({why})")
        else:
            click.echo(escape(f"{rec['time'][11:]} {rec['bus']}   malformed datagram: {rec['malformed']}"))
        if "message" in rec:
            shown += 1

    def stop() -> bool:
        return (count is not None and shown >= count) or deadline.expired

    def ready() -> None:
        click.echo(f"monitoring bus {cfg.bus.name} ({cfg.bus.group}:{cfg.bus.port}); Ctrl-C stops", err=True)

    keyed = not no_key
    if keyed:
        try:
            keys.load(cfg.bus, "module")
        except BusError as e:
            click.echo(f"{e}: showing only that traffic exists", err=True)
            keyed = False
    try:
        watch(cfg.bus, emit, stop, show_acks, ready, keyed, show_members)
    except KeyboardInterrupt:
        pass


commands = [monitor]
