"""The Lot Server (thesis 1.4.4, 6.1.1): the one writer of LOTS, LOT_ENTITIES and LOT_STATUS.

It creates lot entities (one per unit of a lot's quantity), divides, merges and destroys them, and
keeps in LOT_STATUS where each entity is: created, waiting_import, imported, waiting_machine,
running, completed, waiting_export, exported or failed. An entity asks (ENTITY_REQ) to be imported
or exported; the operator decides (IMPORT_LOT / EXPORT_LOT) and LOT_MOVED tells the entity. An
entity that was exported and asks to come back is a new lot (6.1.1): it gets a new lot_id then.

It also reaps: a lot script announces itself (action attach) and is watched as bus peer
lot:<entity>; when that peer leaves (killed, crashed) while its entity is still at work, the
entity is marked failed and MSCHED is asked to cancel its requests and free its machines, so a
dead script leaves nothing reserved behind. A script whose host's agent announced (MOD_DIED) that it
restarts it is not reaped: its new process attaches and resumes the entity (docs/reliability.md);
only if none attaches within RESTART_GRACE, or the agent gave it up (FATAL), is it reaped.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from gwc.config import Config
from gwc.errors import GwcError, Refused
from gwc.ipc.bus import Conversation, Peer
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode, LotState
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S, Handler, Module
from gwc.servers import lot_store
from gwc.servers.common import SERVER_TIMEOUT, Pruner, Server
from gwc.servers.lot_store import FINISHED, IN_CELL, MAX_QUANTITY, NewLot

MAX_CHILDREN = 20  # entities one CREATE_LOT of a lot script may make (each is a process)
RESTART_GRACE = 30.0  # s: a lot script its agent restarts attaches again within this (its start_timeout)
# ENTITY_REQ action -> (the state it moves the entity to, or None; the states it may come from).
ACTIONS: dict[str, tuple[LotState | None, frozenset[LotState]]] = {
    "import": (LotState.WAITING_IMPORT, frozenset({LotState.CREATED, LotState.EXPORTED, LotState.WAITING_IMPORT})),
    "export": (LotState.WAITING_EXPORT, IN_CELL | {LotState.WAITING_EXPORT}),
    "waiting_machine": (
        LotState.WAITING_MACHINE,
        frozenset({LotState.IMPORTED, LotState.WAITING_MACHINE, LotState.RUNNING, LotState.HELD}),
    ),
    "running": (
        LotState.RUNNING,
        frozenset({LotState.IMPORTED, LotState.WAITING_MACHINE, LotState.RUNNING, LotState.HELD}),
    ),
    # A run in doubt past its bound, the script's decision "hold": the operator releases it (RELEASE_LOT).
    "held": (LotState.HELD, frozenset({LotState.WAITING_MACHINE, LotState.RUNNING, LotState.HELD})),
    "completed": (LotState.COMPLETED, IN_CELL),
    "failed": (LotState.FAILED, frozenset(LotState) - {LotState.EXPORTED}),
    "attach": (None, frozenset(LotState) - {LotState.EXPORTED, LotState.FAILED}),
    "state": (None, frozenset(LotState)),
    "destroy": (None, frozenset({LotState.CREATED, LotState.EXPORTED, LotState.FAILED})),
}
# The operator's decisions: conversation -> action -> (the states it needs, the state it leaves, in words).
# An import may come before the entity's script asks for it (created: its script is queued, or has not
# asked yet): the material is in the cell ahead, and the script finds itself imported when it starts.
DECISIONS: dict[str, dict[str, tuple[frozenset[LotState], LotState, str]]] = {
    Conv.IMPORT_LOT: {
        "import": (frozenset({LotState.WAITING_IMPORT, LotState.CREATED}), LotState.IMPORTED, "imported")
    },
    Conv.EXPORT_LOT: {"export": (frozenset({LotState.WAITING_EXPORT}), LotState.EXPORTED, "exported")},
    Conv.RELEASE_LOT: {
        "retry": (frozenset({LotState.HELD}), LotState.RUNNING, "released to retry"),
        "reroute": (frozenset({LotState.HELD}), LotState.RUNNING, "released to reroute"),
        "fail": (frozenset({LotState.HELD}), LotState.FAILED, "released as failed"),
    },
}


def lot_parent(asker: str) -> int | None:
    """The entity a conversation's asker is, when it is a lot script (lot:E): the parent of what it creates."""
    kind, _, ent = asker.partition(":")
    return int(ent) if kind == "lot" and ent.isdigit() else None


class LotServer(Server, Module):
    role = "ls"

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.watched: dict[int, float] = {}  # entity -> when its script was last seen on the bus
        self.restarting: dict[int, float] = {}  # entity -> until when its script's restart is waited for
        self.grace = max(3.0, 2 * cfg.bus.peer_timeout)
        self.pruner = Pruner("ls", "entity history", cfg.record, self.transaction, log)

    def handlers(self) -> dict[str, Handler]:
        return {
            Conv.CREATE_LOT: self.create_lot,
            Conv.ENTITY_REQ: self.entity_request,
            Conv.IMPORT_LOT: self.decision,
            Conv.EXPORT_LOT: self.decision,
            Conv.RELEASE_LOT: self.decision,
            Conv.DIV_MERGE: self.divide_merge,
            Conv.MOD_DIED: self.module_died,
            Conv.LOT_ACTION: self.lot_action,
        }

    # ----------------------------------------------------------------- lifecycle and the reaper

    async def on_bus(self) -> None:
        self.bus.peer_listeners.append(self._peer_changed)

    def on_connect(self, conn: Any) -> None:
        """A cell without history ([record] history = false): lot_status's trigger records nothing."""
        if not self.cfg.record.history:
            conn.execute("select set_config('gwc.record_entities', 'off', false)")
            conn.commit()

    async def on_idle(self) -> None:
        if not self.started:
            return
        now = time.monotonic()
        self.pruner.on_idle(now)
        self.reap_silent(now)

    async def lot_action(self, conv: Conversation) -> None:
        """LOT_ACTION: an operator's action on an entity done through another module (a cancel, told
        MSCHED), kept in the entity's history with who did it."""
        req = self.request(conv)
        if not str(req.action).strip() or not str(req.by).strip():
            raise Refused(AckCode.BAD_MESSAGE, "a lot action needs an action and who did it")
        lot_id = self.transaction(lot_store.record_action(req.entity_id, req.action, req.by, req.note))
        self.log.info("entity %d: %s by %s", req.entity_id, req.action, req.by)
        await self.answer(conv, Msg.LOT_ACTION_ACK, lot_id=lot_id)

    async def on_startup(self) -> str:
        """Watch the scripts of entities at work (they had a script when we were last up)."""
        now = time.monotonic()
        self.watched = {e: now for e in self.transaction(lot_store.attached_entities)}
        self.log.info("watching the scripts of %d entities", len(self.watched))
        return AckCode.ACK_OK

    def _peer_changed(self, name: str, peer: Peer | None) -> None:
        """A watched script's peer left the bus (silence or bye): reap at once, unless it is restarting."""
        kind, _, ent = name.partition(":")
        if peer is not None or kind != "lot" or not ent.isdigit() or not self.started:
            return
        entity = int(ent)
        if entity in self.watched and not self._restarting(entity, time.monotonic()):
            self.watched.pop(entity, None)
            self.spawn(self.reap(entity, f"bus peer {name} left"))

    def _restarting(self, entity: int, now: float) -> bool:
        until = self.restarting.get(entity)
        if until is not None and now > until:
            self.restarting.pop(entity, None)
        return until is not None and now <= until

    async def module_died(self, conv: Conversation) -> None:
        """MOD_DIED (a host's agent): a lot script it restarts is waited for; one it gave up is reaped now."""
        died = self.request(conv)
        kind, _, ent = str(died.module).partition(":")
        if kind != "lot" or not ent.isdigit():
            return
        entity = int(ent)
        if died.restart_in is None:
            self.restarting.pop(entity, None)
            self.watched.pop(entity, None)
            self.spawn(self.reap(entity, f"{died.module} {died.how}, given up by {died.host} ({died.state})"))
            return
        self.restarting[entity] = time.monotonic() + float(died.restart_in) + RESTART_GRACE
        self.log.info("%s died (%s); %s restarts it: its entity waits for it", died.module, died.how, died.host)

    def reap_silent(self, now: float) -> None:
        """Reap the scripts of watched entities not seen on the bus for longer than the grace."""
        peers = self.bus.peers()
        for ent, seen in list(self.watched.items()):
            if f"lot:{ent}" in peers:
                self.watched[ent] = now
            elif now - seen > self.grace and not self._restarting(ent, now):
                self.watched.pop(ent, None)
                self.spawn(self.reap(ent, f"bus peer lot:{ent} not seen for {now - seen:.1f}s"))

    async def reap(self, entity_id: int, why: str) -> None:
        """A lot script died: its entity, if still at work, fails; MSCHED frees what it held."""
        reason = f"lot script died ({why})"

        def fail(cur: Any) -> bool:
            return lot_store.fail_unless_finished(cur, entity_id, reason)

        if not await self.transaction_when_up(fail):  # a dead script is reaped once the database is back
            return
        self.log.warning("entity %d failed: %s; asking msched to cancel and unreserve", entity_id, reason)
        await self.event(f"entity {entity_id} failed: {reason}")
        for cls, msg in (
            (Conv.CANCEL_RE, message(Msg.CANCEL_REQUEST, entity_id=entity_id, by=self.name)),
            (Conv.UNRESERVE, message(Msg.UNRESERVE_ME, entity_id=entity_id, by=self.name)),
        ):
            try:
                answer = await self.ask(cls, msg, "msched", SERVER_TIMEOUT, within=DATABASE_OUTAGE_S)
                self.log.info("%s for entity %d: %s %s", cls, entity_id, answer.ack_code, answer.note or "")
            except GwcError as e:  # ConversationTimeout among them
                self.log.error("%s for dead entity %d not done: %s", cls, entity_id, e)

    # ----------------------------------------------------------------- conversations

    async def create_lot(self, conv: Conversation) -> None:
        """CREATE_LOT (create_lot_entity): a lot (or more of an existing one), one entity per unit."""
        req = self.request(conv)
        if not 0 < req.quantity <= MAX_QUANTITY:
            raise Refused(AckCode.BAD_MESSAGE, f"quantity must be 1..{MAX_QUANTITY}")
        # A lot script creates its own children (6.1: "an OE can actually start other OEs"): new lots only,
        # of its own order, each entity's parent the asker (docs/lot-scripts.md, *Child entities*).
        parent = lot_parent(conv.initiator)
        if parent is not None and (req.lot_id is not None or req.quantity > MAX_CHILDREN):
            why = "a lot script creates a new lot of its own" if req.lot_id is not None else f"{MAX_CHILDREN} at most"
            raise Refused(AckCode.NOT_AUTH, why)
        asked = ("lot_id", "lot_type", "work_order_id", "owner", "priority", "script_id", "request_id")
        params = tuple(str(p) for p in req.result_params or ())
        new = NewLot(
            req.product_id, req.quantity, **{k: req.fields.get(k) for k in asked}, result_params=params, parent=parent
        )
        made = self.transaction(lambda cur: lot_store.create_lot(cur, new))
        ids = ", ".join(map(str, made.entity_ids))
        if made.new:
            children = f", children of entity {parent}" if parent is not None else ""
            self.log.info("lot %d: entities %s created for %s%s", made.lot_id, ids, req.owner or conv.peer, children)
        else:
            self.log.warning(
                "CREATE_LOT %s asked again: lot %d, entities %s, already created", req.request_id, made.lot_id, ids
            )
        note = None if made.new else "already created"
        await self.answer(conv, Msg.CREATE_LOT_ACK, note=note, lot_id=made.lot_id, entity_ids=made.entity_ids)

    async def entity_request(self, conv: Conversation) -> None:
        """ENTITY_REQ: an entity moves itself (import, export, waiting_machine, running, completed,
        failed), attaches its script, reads its state or is destroyed; Notnow if its state forbids it."""
        req = self.request(conv)
        if req.action not in ACTIONS:
            raise Refused(AckCode.BAD_MESSAGE, f"action {req.action!r} is not one of {', '.join(ACTIONS)}")
        if req.action == "failed" and not (req.reason or "").strip():
            raise Refused(AckCode.BAD_MESSAGE, "failed needs a reason")
        if req.action == "attach" and not (req.script_pid or 0) > 0:
            raise Refused(AckCode.BAD_MESSAGE, "attach needs the script's pid")
        target, allowed = ACTIONS[req.action]
        # A move to another state (the usual ENTITY_REQ) is one statement; the rest (or a move that did
        # not apply: the step says why) reads first.
        moved = None
        if target is not None and req.action != "destroy":
            step = lot_store.move(req.entity_id, target, allowed - {target, LotState.EXPORTED}, req.reason, keep=False)
            moved = self.transaction(step)
        if moved is not None:
            done = lot_store.Moved(moved[0], target)
        else:
            entity = req.entity_id, req.action, target, allowed, req.reason, req.script_pid
            done = self.transaction(lambda cur: lot_store.entity_step(cur, *entity))
        self._after(req.entity_id, req.action, done.state, conv)
        if req.action not in ("state", "attach"):
            note = f" ({done.note})" if done.note else ""
            self.log.info("entity %d: %s -> %s%s", req.entity_id, req.action, done.state, note)
        state = done.state.value if done.state else None
        await self.answer(
            conv, Msg.ENTITY_ACK, AckCode.ACK_OK, done.note, lot_id=done.lot_id, state=state, **done.attached
        )
        if req.action in ("import", "export"):
            await self.event(f"entity {req.entity_id} (lot {done.lot_id}) waits to be {req.action}ed")

    def _after(self, entity_id: int, action: str, state: LotState | None, conv: Conversation) -> None:
        """Keep the reaper's watch in step with the entity."""
        if action == "attach" and state not in FINISHED:
            self.watched[entity_id] = time.monotonic()
            self.restarting.pop(entity_id, None)
            self.log.info("entity %d: lot script attached (bus peer %s)", entity_id, conv.peer)
        elif state in FINISHED or action == "destroy":
            self.watched.pop(entity_id, None)
            self.restarting.pop(entity_id, None)

    async def decision(self, conv: Conversation) -> None:
        """IMPORT_LOT / EXPORT_LOT: the operator lets a waiting entity in or out; RELEASE_LOT: a held one
        goes on (retry, reroute) or fails; LOT_MOVED tells the entity."""
        req = self.request(conv)
        ack = Msg.LOT_DECISION_ACK
        if req.action not in DECISIONS[conv.cls]:
            known = ", ".join(DECISIONS[conv.cls])
            raise Refused(AckCode.BAD_MESSAGE, f"{conv.cls} decides {known}, not {req.action!r}")
        action = req.action
        waiting, moved, done = DECISIONS[conv.cls][action]
        by = req.by or conv.peer
        reason = f"held run {done} by {by}" if LotState.HELD in waiting else None

        # The move, or why not: each one statement, run alone (a refusal's read is a snapshot of its own,
        # as it was in one read-committed step).
        what = action if conv.cls in (Conv.IMPORT_LOT, Conv.EXPORT_LOT) else f"release {action}"
        record = (str(what), str(by)) if self.cfg.record.history else None
        row = self.transaction(lot_store.move(req.entity_id, moved, waiting, reason, keep=True, action=record))
        if row is None:  # not moved: why not, refused (Notnow with its lot, or Unknown)
            self.transaction(lot_store.why_not_moved(req.entity_id, waiting))
        lot_id = row[0] if row else None
        await self.answer(conv, ack, lot_id=lot_id)
        if moved in FINISHED:
            self.watched.pop(req.entity_id, None)
        self.log.info("entity %d (lot %s) %s by %s", req.entity_id, lot_id, done, by)
        news = message(Msg.LOT_MOVED, entity_id=req.entity_id, action=action, lot_id=lot_id)
        await self.broadcast(Conv.LOT_MOVED, news)  # the cell's watchers: status line, console, OPC UA
        # The entity's own script hears it addressed to it: lot scripts do not listen to the broadcast,
        # or every lot in the cell would be woken by (and acknowledge) every other lot's move. A script
        # not on the bus now reads its state when it is (gwc/lot/core.py, _wait_moved).
        script = f"lot:{req.entity_id}"
        if script in self.bus.peers():
            (await self.bus.start(Conv.LOT_MOVED, news, to=script)).end()
        await self.event(f"entity {req.entity_id} (lot {lot_id}) {done} by {by}")

    async def divide_merge(self, conv: Conversation) -> None:
        """DIV_MERGE: divide splits `quantity` new entities off one (same lot and state, parent set);
        merge folds other_entity_id into entity_id (the other is destroyed). Only before work starts."""
        req = self.request(conv)
        if req.action not in ("divide", "merge"):
            raise Refused(AckCode.BAD_MESSAGE, f"action {req.action!r} is not divide or merge")
        n = 1 if req.quantity is None else req.quantity
        if req.action == "divide" and not 0 < n <= MAX_QUANTITY:
            raise Refused(AckCode.BAD_MESSAGE, f"quantity must be 1..{MAX_QUANTITY}")
        if req.action == "merge" and (req.other_entity_id is None or req.other_entity_id == req.entity_id):
            raise Refused(AckCode.BAD_MESSAGE, "merge needs another entity (other_entity_id)")
        asker = lot_parent(conv.initiator)  # a lot script divides itself, merges its own children into itself
        if asker is not None and req.entity_id != asker:
            raise Refused(AckCode.NOT_AUTH, f"{conv.initiator} divides and merges itself only")
        asked = req.action, req.entity_id, req.other_entity_id, n, asker
        ids, note = self.transaction(lambda cur: lot_store.divide_merge(cur, *asked))
        self.log.info("%s of entity %d: %s", req.action, req.entity_id, note or ids)
        await self.answer(conv, Msg.DIVIDE_MERGE_ACK, note=note, entity_ids=ids)
