"""The rest of Listing 1's calls: a recipe to and from a reserved machine (`ers_download`, `ers_upload`),
a new recipe version proposed (6.1's "tweek a recipe"), child operation entities (6.1: "an OE can
actually start other OEs if it requires the operation of those OEs"), the Lot Server's division and
merger (1.4.4) and the lot's scrap for the machine's books (1.4.2); see docs/lot-scripts.md.

Each is allowed under the lot key only for what the entity holds, and its server checks it: the WC
for a machine RESERVED_MACHINES gives to the entity, the ERS for a recipe of such a machine (stored
unapproved: the operator approves it), the Lot Server makes what the entity creates its children and
lets it divide itself and merge its own children, the Machine Server books scrap in its own name.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Sequence

from gwc.errors import GwcError, Refused
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, LotState
from gwc.ipc.names import Conv, Msg
from gwc.lot.errors import LotError, LotTimeout, StepRefused
from gwc.lot.runs import MachineRuns
from gwc.lot.spawn import spawn_lot_scripts  # the HI's way: one path (and queue) for every lot script
from gwc.lot.state import EntityState
from gwc.lot.talk import BusLink
from gwc.module import ask
from gwc.retry import Deadline

# A child entity is done when it is in one of these: it no longer works in the cell.
CHILD_DONE = frozenset({LotState.COMPLETED, LotState.WAITING_EXPORT, LotState.EXPORTED, LotState.FAILED})
CHILD_POLL = 0.5  # s between reads of the children's states while waiting for them


class Holdings:
    """Recipes to, from and for the entity's machines; its scrap; the entity's children."""

    def __init__(self, facts: EntityState, link: BusLink, runs: MachineRuns) -> None:
        self.facts = facts
        self.link = link
        self.runs = runs
        self._children_asked = 0  # start_child calls in this process: the n-th asks with request id ...child.n

    # ----------------------------------------------------------------- recipes

    def download_recipe(self, machine_id: str, recipe_id: str) -> None:
        """Listing 1's ers_download: DNLD_ME to the machine's WC, which fetches the recipe's approved
        version from the ERS and gives it to the machine. The machine must be reserved to this entity
        (StepRefused Not_Auth otherwise) and Idle."""
        self._wc_step(Conv.DNLD_ME, message(Msg.DOWNLOAD_ME, machine_id=machine_id, recipe_id=recipe_id))
        self.facts.log.info("recipe %s downloaded to %s", recipe_id, machine_id)

    def upload_recipe(self, machine_id: str, recipe_id: str) -> int:
        """Listing 1's ers_upload: UPLD_ME to the machine's WC, which reads the machine's copy of the
        recipe and has the ERS store it; returns its version (a new, unapproved one if the machine's
        copy changed, else the version it equals). The machine must be reserved to this entity."""
        ack = self._wc_step(Conv.UPLD_ME, message(Msg.UPLOAD_ME, machine_id=machine_id, recipe_id=recipe_id))
        self.facts.log.info(
            "recipe %s uploaded from %s: version %s (%s)", recipe_id, machine_id, ack.version, ack.note or ""
        )
        return int(ack.version or 0)

    def propose_recipe(self, recipe_id: str, content: str) -> int:
        """RECIPE_PUT to the ERS: `content` stored as a new version of the recipe, unapproved (nothing
        runs it until the operator approves it: `gwc recipe approve`). Only a known recipe of a machine
        reserved to this entity (StepRefused Not_Auth otherwise). Returns the version."""
        msg = message(Msg.RECIPE_STORE, recipe_id=recipe_id, content=content, by=self.facts.name)
        ack = self._checked(Conv.RECIPE_PUT, self.link.ask_once(Conv.RECIPE_PUT, msg, "ers"), f"recipe {recipe_id}")
        self.facts.log.info("recipe %s v%s proposed (%s)", recipe_id, ack.version, ack.note or "new")
        return int(ack.version or 0)

    def _wc_step(self, cls: str, first: Message) -> Message:
        """DNLD_ME / UPLD_ME: asked once (a download is not repeated blindly), given up if the machine is lost."""
        ack = self.runs.ask_wc(cls, first, str(first.machine_id), 0, self.facts.timeouts.setup)
        return self._checked(cls, ack, str(first.machine_id))

    def _checked(self, cls: str, ack: Message, what: str) -> Message:
        if ack.ack_code != AckCode.ACK_OK:
            self.facts.log.error("%s for %s refused: %s %s", cls, what, ack.ack_code, ack.note or "")
            raise StepRefused(cls, str(ack.ack_code), f"{cls} for {what} refused: {ack.ack_code} ({ack.note or '-'})")
        return ack

    # ----------------------------------------------------------------- scrap

    def scrap(self, machine_id: str, machine_run_id: int, parts: int = 1, reason: str | None = None) -> None:
        """The lot's verdict: `parts` made by that run on that machine are scrap (1.4.2: the Machine
        Server keeps track of scraps). SCRAP_RPT to the Machine Server, asked again while it is away (a
        repeat is counted once)."""
        msg = message(
            Msg.SCRAP_REPORT,
            entity_id=self.facts.entity_id,
            machine_id=machine_id,
            machine_run_id=machine_run_id,
            parts=parts,
            reason=reason[:500] if reason else None,
        )
        self._checked(Conv.SCRAP_RPT, self.link.ask(Conv.SCRAP_RPT, msg, "ms"), f"run {machine_run_id} on {machine_id}")
        self.facts.log.info("scrap: %d part(s) of run %d on %s (%s)", parts, machine_run_id, machine_id, reason or "-")

    # ----------------------------------------------------------------- children

    def start_child(self, product_id: str, quantity: int = 1, script_id: str | None = None) -> list[int]:
        """Start other operation entities (6.1): a new lot of `quantity` of `product_id` (its product's
        lot script, or `script_id`), in this entity's work order, each entity this one's child; their
        lot scripts started as the Human Interface starts an order's. Returns the children's entity ids.

        The n-th call of a script's run asks with the same request id every time, so a script its agent
        restarted gets the children its first run made, not new ones (and their scripts, running, are
        left as they are)."""
        self._children_asked += 1
        request_id = f"{self.facts.name}.child.{self._children_asked}"
        try:
            lot_id, children = create_lot(
                self.link.need(),
                product_id,
                quantity,
                script_id=script_id,
                priority=self.facts.priority,
                timeout=self.facts.timeouts.answer,
                within=self.facts.timeouts.retry,
                request_id=request_id,
            )
        except LotError as e:
            raise StepRefused(Conv.CREATE_LOT, _code_of(str(e)), str(e)) from e
        started = spawn_lot_scripts(self.facts.cfg, children)
        self.facts.log.info(
            "lot %d of %d %s started as children: entities %s (pids %s)",
            lot_id,
            quantity,
            product_id,
            ", ".join(map(str, children)),
            ", ".join(str(started[c] or "queued") for c in children),
        )
        self.facts.traveller.setdefault("children", []).extend(children)
        self.facts.save()
        return children

    def divide(self, quantity: int = 1, start_scripts: bool = True) -> list[int]:
        """The Lot Server's division (1.4.4): `quantity` new entities split off this one, in its lot and
        state (only while it is created or imported), each its child; their lot scripts started as
        start_child's are, unless `start_scripts` is false. Returns the new entities."""
        try:
            new = divide_entity(self.link.need(), self.facts.entity_id, quantity, self.facts.timeouts.answer)
        except GwcError as e:
            raise StepRefused(Conv.DIV_MERGE, str(getattr(e, "ack_code", AckCode.UNKNOWN)), str(e)) from e
        self.facts.log.info("divided: new entities %s", ", ".join(map(str, new)))
        if start_scripts and new:
            spawn_lot_scripts(self.facts.cfg, new)
        return new

    def merge(self, child: int) -> None:
        """The Lot Server's merger (1.4.4): a child of this entity (divided or started by it), of its lot
        and state, folded into it (the child is destroyed; its script, if any, fails on its next step)."""
        try:
            merge_entities(self.link.need(), self.facts.entity_id, child, self.facts.timeouts.answer)
        except GwcError as e:
            raise StepRefused(Conv.DIV_MERGE, str(getattr(e, "ack_code", AckCode.UNKNOWN)), str(e)) from e
        self.facts.log.info("merged entity %d into this one", child)

    def wait_for_children(self, children: Sequence[int], timeout: float | None = None) -> dict[int, str]:
        """Wait until every child is done (completed, waiting for or past export, or failed), reading
        their states from the Lot Server (ENTITY_REQ state) every half second. Returns each one's state;
        LotTimeout past `timeout` (Timeouts.run by default). A failed child is for the script to judge."""
        deadline = Deadline(self.facts.timeouts.run if timeout is None else timeout)
        states: dict[int, str] = {}
        while True:
            for child in children:
                if states.get(child) not in CHILD_DONE:
                    states[child] = self._child_state(child)
            if all(s in CHILD_DONE for s in states.values()):
                self.facts.log.info("children done: %s", ", ".join(f"{c} {s}" for c, s in states.items()))
                return states
            if deadline.expired:
                raise LotTimeout(
                    f"entity {self.facts.entity_id}: children not done in time: "
                    + ", ".join(f"{c} {s}" for c, s in states.items())
                )
            time.sleep(CHILD_POLL)

    def _child_state(self, child: int) -> str:
        msg = message(Msg.ENTITY_REQUEST, entity_id=child, action="state")
        try:
            ack = self.link.ask(Conv.ENTITY_REQ, msg, "ls")
        except GwcError as e:
            raise LotError(f"entity {self.facts.entity_id}: state of child {child} not read: {e}") from e
        if ack.ack_code != AckCode.ACK_OK or ack.state is None:
            raise LotError(f"entity {self.facts.entity_id}: child {child}: {ack.ack_code} {ack.note or ''}")
        return str(ack.state)


def _code_of(text: str) -> str:
    """The ack code create_lot's LotError names (its message says `...: CODE (note)`)."""
    for code in AckCode:
        if f": {code.value}" in text:
            return code.value
    return AckCode.UNKNOWN.value


# ----------------------------------------------------------------------------- the Lot Server's 1.4.4


def create_lot(
    bus: BlockingBus,
    product_id: str,
    quantity: int,
    *,
    work_order_id: int | None = None,
    owner: str | None = None,
    priority: int | None = None,
    script_id: str | None = None,
    lot_type: str | None = None,
    timeout: float = 10.0,
    within: float = 60.0,
    request_id: str | None = None,
) -> tuple[int, list[int]]:
    """CREATE_LOT: ask the Lot Server for a lot of `quantity` entities. Returns (lot_id, entity_ids).

    A Lot Server that does not answer (it died after creating the lot, or is restarting) is asked
    again for up to `within` seconds with the same request_id, so the lot is made once: a repeat is
    answered with what the first request made. Give request_id to make it survive this call too.
    """
    request_id = request_id or f"{bus.bus.name}.{secrets.token_hex(8)}"
    ack = bus.run(
        ask(
            bus.bus,
            Conv.CREATE_LOT,
            message(
                Msg.CREATE_LOT_ENTITY,
                product_id=product_id,
                quantity=quantity,
                work_order_id=work_order_id,
                owner=owner,
                priority=priority,
                script_id=script_id,
                lot_type=lot_type,
                request_id=request_id,
            ),
            "ls",
            timeout,
            within=within,
        )
    )
    if ack.ack_code != AckCode.ACK_OK or ack.lot_id is None:
        raise LotError(
            f"the Lot Server refused to create a lot of {quantity} {product_id}: {ack.ack_code}"
            + (f" ({ack.note})" if ack.note else "")
        )
    return int(ack.lot_id), [int(e) for e in ack.entity_ids or []]


def _lot_server(bus: BlockingBus, first: Message, timeout: float, what: str) -> Message:
    cls = Conv.DIV_MERGE if first.name == Msg.DIVIDE_MERGE else Conv.ENTITY_REQ
    ack = bus.run(ask(bus.bus, cls, first, "ls", timeout))
    if ack.ack_code == AckCode.UNKNOWN:
        raise GwcError(f"{what}: {ack.note or 'unknown entity'} (see `gwc lots`)")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, f"{what}: {ack.note or ack.ack_code}")
    return ack


def divide_entity(bus: BlockingBus, entity_id: int, quantity: int = 1, timeout: float = 10.0) -> list[int]:
    """Divide (1.4.4): `quantity` new entities split off one that is created or imported, in its lot and
    state, each its child. Returns the new entities (without the one divided)."""
    msg = message(Msg.DIVIDE_MERGE, entity_id=entity_id, action="divide", quantity=quantity)
    ack = _lot_server(bus, msg, timeout, f"divide entity {entity_id}")
    return [int(e) for e in ack.entity_ids or [] if int(e) != entity_id]


def merge_entities(bus: BlockingBus, entity_id: int, other_id: int, timeout: float = 10.0) -> None:
    """Merge (1.4.4): `other_id` folded into `entity_id` (the other is destroyed); both created or
    imported, of one lot and one state."""
    msg = message(Msg.DIVIDE_MERGE, entity_id=entity_id, action="merge", other_entity_id=other_id)
    _lot_server(bus, msg, timeout, f"merge entity {other_id} into {entity_id}")


def destroy_entity(bus: BlockingBus, entity_id: int, timeout: float = 10.0) -> None:
    """Destroy (1.4.4): an entity that is created (not started), exported or failed leaves the lists; its
    rows stay, marked destroyed (the history keeps it)."""
    msg = message(Msg.ENTITY_REQUEST, entity_id=entity_id, action="destroy")
    _lot_server(bus, msg, timeout, f"destroy entity {entity_id}")
