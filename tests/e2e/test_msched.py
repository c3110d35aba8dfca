"""MSCHED end to end: every conversation and ack code, over the real bus and database.

Each test runs a cell whose only module is MSCHED, a real process.

The test's own bus plays the lot entities (MACH_REQ, CANCEL_RE, UNRESERVE), the WCs (ACC_TYP_C) and
the Machine Server (UPD_ME_ST broadcasts); machine_status rows are set up with the superuser
connection, as the Machine Server would have written them.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import pytest

from gwc.cell import startup
from gwc.errors import ConversationTimeout
from gwc.ipc import Batch, BlockingBus, BlockingConversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.msched.store import SWEEP_WORK
from tests.harness import CellHarness, wait_for

T = 20.0  # generous deadlines: the machines are shared


def add_entities(
    cell: CellHarness, *entity_ids: int, priority: int = 20, state: str = "waiting_machine", lot_id: int | None = None
) -> None:
    """Lot entities as the Lot Server would have made them (one lot per call)."""
    lot = lot_id or 1000 + entity_ids[0]
    with cell.db() as conn:
        conn.execute(
            "insert into lots (lot_id, product_id, priority) values (%s, 'alum_chess_set', %s)", (lot, priority)
        )
        for e in entity_ids:
            conn.execute("insert into lot_entities (entity_id, lot_id) values (%s, %s)", (e, lot))
            conn.execute("insert into lot_status (entity_id, lot_id, state) values (%s, %s, %s)", (e, lot, state))


def set_status(cell: CellHarness, status: str, *machines: str) -> None:
    """What the Machine Server writes in MACHINE_STATUS."""
    with cell.db() as conn:
        conn.execute("update machine_status set status = %s where machine_id = any(%s)", (status, list(machines)))


def ask(cell: CellHarness, cls: str, first: Message, *more: Message) -> Message:
    conv, batch = cell.bus.request(cls, first, *more, to="msched", timeout=T)
    conv.end()
    return batch.first


def accept(cell: CellHarness, machine: str, op_types: list[str] | None = None) -> Message:
    """ACC_TYP_C as the machine's WC sends it (default: all it has recipes for)."""
    return ask(
        cell,
        "ACC_TYP_C",
        message("Chg_Accept_Type", machine_id=machine, op_types=["*"] if op_types is None else op_types),
    )


def machines_up(cell: CellHarness, *machines: str) -> None:
    """Machines Idle and accepting everything, and MSCHED told (as MS and the WCs would)."""
    set_status(cell, "Idle", *machines)
    for m in machines:
        assert accept(cell, m).ack_code == AckCode.ACK_OK


def broadcast_status(cell: CellHarness, machine: str, status: str, previous: str | None = None) -> None:
    """UPD_ME_ST, as the Machine Server broadcasts it after writing MACHINE_STATUS."""
    set_status(cell, status, machine)
    conv = cell.bus.start(
        "UPD_ME_ST", message("Update_ME_Status", machine_id=machine, status=status, previous=previous)
    )
    conv.end()


def unreserve(cell: CellHarness, entity: int, machine: str | None = None) -> Message:
    return ask(cell, "UNRESERVE", message("Unreserve_Me", entity_id=entity, machine_id=machine, by="test"))


def cancel(cell: CellHarness, request_key: int | None = None, entity: int | None = None) -> Message:
    return ask(cell, "CANCEL_RE", message("Cancel_Request", request_key=request_key, entity_id=entity, by="test"))


@dataclass
class Request:
    """One MACH_REQ conversation, played as the lot entity plays it."""

    cell: CellHarness
    entity: int
    machines: list[str]
    op_type: str = "dummy_op"
    priority: int | None = None
    alt_group: str | None = None
    conv: BlockingConversation | None = None
    ack: Message | None = None
    comp_batch: Batch | None = field(default=None, repr=False)

    def send(self, num_machines: int | None = None) -> Request:
        n = len(self.machines) if num_machines is None else num_machines
        self.conv, batch = self.cell.bus.request(
            "MACH_REQ",
            message(
                "Machine_Request",
                entity_id=self.entity,
                op_type=self.op_type,
                num_machines=n,
                priority=self.priority,
                alt_group=self.alt_group,
            ),
            *[message("Machine_Entry", machine_id=m) for m in self.machines],
            to="msched",
            timeout=T,
        )
        self.ack = batch.first
        if self.ack.ack_code != AckCode.ACK_OK:
            self.conv.end()
        return self

    @property
    def key(self) -> int:
        assert self.ack is not None and self.ack.request_key is not None, self.ack
        return int(self.ack.request_key)

    def comp(self, timeout: float = T, acknowledge: bool = True) -> Message:
        """Wait for the Machine_Req_Comp and (by default) answer Request_Comp_Ack."""
        assert self.conv is not None
        self.comp_batch = self.conv.expect("Machine_Req_Comp", timeout=timeout)
        if acknowledge:
            self.conv.send(message("Request_Comp_Ack", entity_id=self.entity, ack_code=AckCode.ACK_OK))
            self.conv.end()
        return self.comp_batch.first

    @property
    def reserved(self) -> list[str]:
        assert self.comp_batch is not None
        return [m.machine_id for m in self.comp_batch.messages[1:]]


def request(cell: CellHarness, entity: int, *machines: str, **kw: Any) -> Request:
    return Request(cell, entity, list(machines), **kw).send()


def reservations(cell: CellHarness) -> dict[str, int]:
    return {m: int(e) for m, e in cell.query("select machine_id, entity_id from reserved_machines")}


def queued_keys(cell: CellHarness) -> list[int]:
    return [int(r[0]) for r in cell.query("select distinct request_key from request_machines order by 1")]


def wait_queued(cell: CellHarness, n: int) -> None:
    wait_for(lambda: len(queued_keys(cell)) == n, T, f"{n} request(s) queued")


def msched_cell(make_cell: Any, **config: Any) -> CellHarness:
    """A private cell whose only module is MSCHED (not started yet)."""
    return make_cell(machines=[], modules=("msched",), **config)


# ----------------------------------------------------------------------------- the conversations


def test_request_bound_when_machine_free(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1")
    first = request(cell, 1, "wc1")
    assert first.ack.ack_code == AckCode.ACK_OK
    comp = first.comp()
    assert comp.ack_code == AckCode.ACK_OK and comp.request_key == first.key and comp.num_machines == 1
    assert first.reserved == ["wc1"] and reservations(cell) == {"wc1": 1}
    second = request(cell, 2, "wc1")
    wait_queued(cell, 1)
    assert unreserve(cell, 1).ack_code == AckCode.ACK_OK
    assert second.comp().ack_code == AckCode.ACK_OK
    assert reservations(cell) == {"wc1": 2}


def test_lifecycle_startup_then_shutdown_answers_every_waiting_request(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched", start=False)
    assert cell.bus.peers()["msched"].interest == frozenset({"STARTUP"})
    add_entities(cell, 1, 2, 3)
    set_status(cell, "Idle", "wc1")
    # Not started: a request is refused Notnow, never queued.
    refused = request(cell, 1, "wc1")
    assert refused.ack.ack_code == AckCode.NOTNOW

    assert startup(cell.bus, "msched") == "started"
    wait_for(
        lambda: (
            cell.bus.peers()["msched"].interest
            >= {"SHUTDOWN", "MACH_REQ", "CANCEL_RE", "UPD_ME_ST", "ACC_TYP_C", "UNRESERVE"}
        ),
        T,
        "msched's busy interest",
    )
    assert startup(cell.bus, "msched") == "already started"
    # Nothing accepted on wc1 yet: both requests wait.
    waiting = [request(cell, 2, "wc1"), request(cell, 3, "wc1")]
    wait_queued(cell, 2)

    conv, batch = cell.bus.request("SHUTDOWN", message("Shutdown_Request", module="msched"), to="msched", timeout=T)
    assert batch.first.ack_code == AckCode.ACK_OK
    comps = [r.comp(acknowledge=False) for r in waiting]
    assert [c.ack_code for c in comps] == [AckCode.NO_MACHINE, AckCode.NO_MACHINE]
    assert [c.request_key for c in comps] == [r.key for r in waiting]
    # Shutdown_Complete only once every Machine_Req_Comp was acknowledged.
    with pytest.raises(ConversationTimeout):
        conv.next_message(0.5)
    for r in waiting:
        r.conv.send(message("Request_Comp_Ack", entity_id=r.entity, ack_code=AckCode.ACK_OK))
        r.conv.end()
    done = conv.expect("Shutdown_Complete", timeout=T).first
    conv.end()
    assert done.ack_code == AckCode.ACK_OK and "2 waiting" in (done.note or "")
    assert queued_keys(cell) == []
    wait_for(lambda: cell.bus.peers()["msched"].interest == frozenset({"STARTUP"}), T, "msched back to STARTUP only")
    wait_for(lambda: cell.query("select count(*) from request_outcomes")[0][0] == 0, T, "the answers forgotten")


def test_machine_request_ack_codes(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    add_entities(cell, 9, state="failed")
    machines_up(cell, "wc1", "wc2")  # wc3 stays Shutdown
    assert request(cell, 1, "nosuch").ack.ack_code == AckCode.NO_MACHINE
    assert request(cell, 1, "wc1", "wc3").ack.ack_code == AckCode.NO_MACHINE
    assert request(cell, 77, "wc1").ack.ack_code == AckCode.UNKNOWN
    assert request(cell, 9, "wc1").ack.ack_code == AckCode.NOTNOW
    assert request(cell, 1, "wc1", op_type="nosuch_op").ack.ack_code == AckCode.UNKNOWN
    assert Request(cell, 1, ["wc1", "wc2"]).send(num_machines=3).ack.ack_code == AckCode.BAD_MESSAGE
    assert request(cell, 1, "wc1", "wc1").ack.ack_code == AckCode.BAD_MESSAGE
    assert queued_keys(cell) == [] and reservations(cell) == {}
    # A valid request of two machines: ACK_OK, then one Machine_Req_Comp with both, in entry order.
    both = request(cell, 1, "wc2", "wc1")
    assert both.ack.ack_code == AckCode.ACK_OK
    comp = both.comp()
    assert comp.ack_code == AckCode.ACK_OK and comp.num_machines == 2 and comp.entity_id == 1
    assert both.reserved == ["wc2", "wc1"]
    assert reservations(cell) == {"wc1": 1, "wc2": 1}
    run_ids = cell.query("select distinct machine_run_id, request_key from reserved_machines")
    assert run_ids == [(comp.machine_run_id, both.key)]
    # Keys come from MAX_VALUES.
    assert cell.query("select value from max_values where type = 'MACH_R_KEY'")[0][0] == both.key


def test_cancel_and_unreserve_ack_codes(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2, 3)
    machines_up(cell, "wc1", "wc2")
    holder = request(cell, 1, "wc1")
    holder.comp()
    a = request(cell, 2, "wc1")
    b = request(cell, 3, "wc1")
    wait_queued(cell, 2)
    # Cancel by key: the entity hears REQ_CANCEL in its MACH_REQ conversation, the canceller ACK_OK.
    ack = cancel(cell, a.key)
    assert (ack.ack_code, ack.cancelled) == (AckCode.ACK_OK, 1)
    assert a.comp().ack_code == AckCode.REQ_CANCEL
    assert cancel(cell, a.key).ack_code == AckCode.REQ_KEY_U  # nothing left to cancel
    assert cancel(cell, 424242).ack_code == AckCode.REQ_KEY_U
    assert cancel(cell).ack_code == AckCode.BAD_MESSAGE
    # Cancel by entity.
    ack = cancel(cell, entity=3)
    assert (ack.ack_code, ack.cancelled) == (AckCode.ACK_OK, 1)
    assert b.comp().ack_code == AckCode.REQ_CANCEL
    assert queued_keys(cell) == []
    # Unreserve: Not_Reserv for a machine the entity does not hold, ACK_OK and freed=n otherwise.
    assert unreserve(cell, 2, "wc1").ack_code == AckCode.NOT_RESERVED
    assert unreserve(cell, 1, "wc2").ack_code == AckCode.NOT_RESERVED
    ack = unreserve(cell, 1)
    assert (ack.ack_code, ack.freed) == (AckCode.ACK_OK, 1)
    assert reservations(cell) == {}
    assert unreserve(cell, 1).ack_code == AckCode.NOT_RESERVED


def test_accept_type_change(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1)
    set_status(cell, "Idle", "wc1")
    assert accept(cell, "nosuch").ack_code == AckCode.UNKNOWN
    assert accept(cell, "wc1", ["nosuch_op"]).ack_code == AckCode.UNKNOWN
    assert accept(cell, "wc1", [7]).ack_code == AckCode.BAD_MESSAGE  # type: ignore[list-item]
    assert accept(cell, "wc1", ["measure"]).ack_code == AckCode.ACK_OK
    assert accept(cell, "wc1", ["dummy_op", "nosuch_op"]).ack_code == AckCode.UNKNOWN  # and changes nothing
    assert cell.query("select op_type from accept_types where machine_id = 'wc1'") == [("measure",)]
    r = request(cell, 1, "wc1", op_type="dummy_op")
    wait_queued(cell, 1)  # wc1 accepts only measure
    assert accept(cell, "wc1", []).ack_code == AckCode.ACK_OK
    assert cell.query("select count(*) from accept_types where machine_id = 'wc1'")[0][0] == 0
    assert accept(cell, "wc1").ack_code == AckCode.ACK_OK  # ['*']: what op_machine_recipe has for wc1
    accepted = {t for (t,) in cell.query("select op_type from accept_types where machine_id = 'wc1'")}
    assert (
        accepted
        == {t for (t,) in cell.query("select distinct op_type from op_machine_recipe where machine_id = 'wc1'")}
        >= {"dummy_op", "measure"}
    )
    assert r.comp().ack_code == AckCode.ACK_OK  # adding dummy_op ran the scheduler


# ----------------------------------------------------------------------------- the thesis's demonstration (7.2, 7.5)


def test_lots_asking_for_the_same_machine_are_served_fifo(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2, 3, 4, 5)
    machines_up(cell, "wc1")
    lots = [request(cell, e, "wc1") for e in (1, 2, 3, 4, 5)]
    wait_queued(cell, 4)
    for lot in lots:  # each unreserve hands wc1 to the oldest request still waiting, and to no other
        assert lot.comp().ack_code == AckCode.ACK_OK
        assert reservations(cell) == {"wc1": lot.entity}
        assert unreserve(cell, lot.entity).ack_code == AckCode.ACK_OK


def test_shutdown_machine_with_alternative_is_rerouted(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2, 3, 4)
    machines_up(cell, "wc1", "wc2")
    holder = request(cell, 1, "wc1")
    holder2 = request(cell, 4, "wc2")
    holder.comp(), holder2.comp()
    only_wc1 = request(cell, 2, "wc1")
    alt_a = request(cell, 3, "wc1")  # entity 3: wc1 OR wc2
    alt_b = request(cell, 3, "wc2")
    wait_queued(cell, 3)
    broadcast_status(cell, "wc1", "Shutdown", "Idle")
    # Entity 2 had no alternative: NO_MACHINE. Entity 3 still waits for wc2, untold.
    assert only_wc1.comp().ack_code == AckCode.NO_MACHINE
    wait_queued(cell, 1)
    assert queued_keys(cell) == [alt_b.key]
    with pytest.raises(ConversationTimeout):
        alt_a.conv.next_message(0.3)
    # wc2 frees: entity 3 gets its alternative; the dead request ends REQ_CANCEL.
    assert unreserve(cell, 4).ack_code == AckCode.ACK_OK
    comp = alt_b.comp()
    assert comp.ack_code == AckCode.ACK_OK and alt_b.reserved == ["wc2"]
    dead = alt_a.comp()
    assert dead.ack_code == AckCode.REQ_CANCEL and str(alt_b.key) in dead.note
    # The shut-down machine is never scheduled again (it is still reserved by entity 1 meanwhile).
    assert unreserve(cell, 1).ack_code == AckCode.ACK_OK
    assert request(cell, 2, "wc1").ack.ack_code == AckCode.NO_MACHINE
    assert "wc1" not in reservations(cell)


def test_last_alternative_lost_tells_every_request_no_machine(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1", "wc2")
    request(cell, 1, "wc1", "wc2").comp()  # entity 1 holds both
    a, b = request(cell, 2, "wc1"), request(cell, 2, "wc2")
    wait_queued(cell, 2)
    broadcast_status(cell, "wc1", "Shutdown")
    wait_queued(cell, 1)
    broadcast_status(cell, "wc2", "Shutdown")
    assert {a.comp().ack_code, b.comp().ack_code} == {AckCode.NO_MACHINE}
    assert queued_keys(cell) == []


def test_machine_added_while_cell_runs_is_used(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1")
    request(cell, 1, "wc1").comp()
    waiting = request(cell, 2, "wc1", "wc2", op_type="measure")
    assert waiting.ack.ack_code == AckCode.NO_MACHINE  # wc2 is Shutdown: refused at once
    waiting = request(cell, 2, "wc4")
    assert waiting.ack.ack_code == AckCode.NO_MACHINE
    # wc4 starts (MS says Idle, its WC says what it accepts): the next request for it is served.
    broadcast_status(cell, "wc4", "Idle", "Shutdown")
    waiting = request(cell, 2, "wc4")
    wait_queued(cell, 1)  # up, but accepts nothing yet
    assert accept(cell, "wc4").ack_code == AckCode.ACK_OK
    assert waiting.comp().ack_code == AckCode.ACK_OK and waiting.reserved == ["wc4"]


def test_dead_entity_does_not_hold_up_the_scheduler(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2, 3)
    machines_up(cell, "wc1", "wc2")
    request(cell, 1, "wc1").comp()
    with BlockingBus("lot:2", cell.cfg.bus, cell.log) as ghost_bus:  # entity 2 asks, then dies
        conv, batch = ghost_bus.request(
            "MACH_REQ",
            message("Machine_Request", entity_id=2, op_type="dummy_op", num_machines=1),
            message("Machine_Entry", machine_id="wc1"),
            to="msched",
            timeout=T,
        )
        assert batch.first.ack_code == AckCode.ACK_OK
    assert unreserve(cell, 1).ack_code == AckCode.ACK_OK  # wc1 goes to the dead entity 2
    started = time.monotonic()
    alive = request(cell, 3, "wc2")
    assert alive.comp().ack_code == AckCode.ACK_OK
    assert time.monotonic() - started < 5, "the scheduler waited for a dead entity's acknowledgement"
    assert reservations(cell) == {"wc1": 2, "wc2": 3}


# ----------------------------------------------------------------------------- alternatives (BUG-6)


def test_alternative_arriving_after_its_group_was_bound_is_cancelled_not_queued(make_cell: Any) -> None:
    """BUG-6: an entity's second alternative arrived just after the first was bound; it was queued
    and outlived the entity. With alt_group it is answered REQ_CANCEL at once: nothing queued, nothing bound."""
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1", "wc2")
    request(cell, 2, "wc2").comp()  # entity 2 holds wc2: a request for it would wait
    first = request(cell, 1, "wc1", alt_group="step1")  # wc1 is free: bound at once
    assert first.comp().ack_code == AckCode.ACK_OK and first.reserved == ["wc1"]

    late = request(cell, 1, "wc2", alt_group="step1")
    assert (late.ack.ack_code, late.ack.request_key) == (AckCode.REQ_CANCEL, None)
    assert late.ack.note == f"alternative {first.key} already satisfied"
    assert queued_keys(cell) == [] and reservations(cell) == {"wc1": 1, "wc2": 2}
    assert cell.log_has("msched", f"alt_group step1 refused: REQ_CANCEL alternative {first.key} already satisfied")
    # The group stays satisfied after its machine is given back (until the entity finishes).
    assert unreserve(cell, 1).ack_code == AckCode.ACK_OK
    assert request(cell, 1, "wc1", alt_group="step1").ack.ack_code == AckCode.REQ_CANCEL
    assert reservations(cell) == {"wc2": 2}

    # Without alt_group, and with a group not served yet, requests queue as before.
    plain = request(cell, 1, "wc2")
    assert plain.ack.ack_code == AckCode.ACK_OK
    other = request(cell, 2, "wc2", alt_group="step1")  # another entity's group of the same name
    assert other.ack.ack_code == AckCode.ACK_OK
    wait_queued(cell, 2)
    assert Request(cell, 1, ["wc1"], alt_group="").send().ack.ack_code == AckCode.BAD_MESSAGE
    assert unreserve(cell, 2).ack_code == AckCode.ACK_OK
    assert plain.comp().ack_code == AckCode.ACK_OK and reservations(cell) == {"wc2": 1}
    assert queued_keys(cell) == [other.key]


def test_finished_entity_is_never_bound_and_its_orphan_request_ends(make_cell: Any) -> None:
    """A request queued without alt_group outlives its entity: the pass never binds it, the
    periodic sweep ends it REQ_CANCEL, frees the machine the finished entity still held (it could
    not unreserve it: the database was away) and forgets the entity's satisfied groups."""
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1", "wc2")
    request(cell, 2, "wc1").comp()
    served = request(cell, 1, "wc2", alt_group="step1")
    assert served.comp().ack_code == AckCode.ACK_OK
    orphan = request(cell, 1, "wc1")
    wait_queued(cell, 1)
    groups = cell.query("select entity_id, alt_group, request_key from satisfied_alt_groups")
    assert groups == [(1, "step1", served.key)]

    with cell.db() as conn:  # the entity finishes (as the Lot Server records it); its orphan still waits
        conn.execute("update lot_status set state = 'completed' where entity_id = 1")
    assert unreserve(cell, 2).ack_code == AckCode.ACK_OK  # wc1 free: the pass must not give it to entity 1
    assert "wc1" not in reservations(cell)
    comp = orphan.comp()  # the sweep ([msched] sweep_s, 5 s)
    assert (comp.ack_code, comp.note) == (AckCode.REQ_CANCEL, "entity finished")
    assert queued_keys(cell) == [] and reservations(cell) == {}
    assert cell.query("select count(*) from satisfied_alt_groups")[0][0] == 0


def test_a_resting_msched_sweeps_with_one_read(make_cell: Any) -> None:
    """Nothing queued, reserved or left of a finished entity: the periodic sweep ([msched] sweep_s, 5 s)
    is its one look at the queue (store.SWEEP_WORK), alone, not a transaction: it stays MSCHED's last
    statement. (That a sweep with work still runs: the test above.)"""
    cell = msched_cell(make_cell)
    cell.start("msched")

    def last_statement() -> str | None:
        rows = cell.query("select query from pg_stat_activity where application_name = 'gwc_msched'")
        return rows[0][0] if rows else None

    wait_for(lambda: last_statement() == SWEEP_WORK, 15, "MSCHED's sweep to look at the queue")
    held_until = time.monotonic() + 1.0
    while time.monotonic() < held_until:  # no transaction follows the look
        assert last_statement() == SWEEP_WORK
        time.sleep(0.05)


# ----------------------------------------------------------------------------- the operator's screen (MREQ)


def _gwc(cell: CellHarness, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=cell.env(), capture_output=True, text=True, timeout=60
    )


def test_hi_lists_the_queue_and_cancels_a_request(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1", "wc2")
    holder = request(cell, 1, "wc1", "wc2")
    holder.comp()
    waiting = request(cell, 2, "wc1")
    wait_queued(cell, 1)

    listed = _gwc(cell, "requests", "--json")
    assert listed.returncode == 0, listed.stderr
    screen = json.loads(listed.stdout)[0]
    assert [(r["request_key"], r["entity_id"], r["machines"]) for r in screen["requests"]] == [(waiting.key, 2, "wc1")]
    assert {r["machine_id"]: r["entity_id"] for r in screen["reserved"]} == {"wc1": 1, "wc2": 1}
    human = _gwc(cell, "requests")
    assert human.returncode == 0 and "REQUEST_KEY" in human.stdout and "MACHINE_RUN_ID" in human.stdout

    done = _gwc(cell, "cancel", str(waiting.key))
    assert done.returncode == 0, done.stderr
    assert "cancelled 1" in done.stdout
    assert waiting.comp().ack_code == AckCode.REQ_CANCEL

    again = _gwc(cell, "cancel", str(waiting.key))
    assert again.returncode != 0
    err = again.stderr.strip().splitlines()
    assert len(err) == 1 and "REQ_KEY_U" in err[0] and "Traceback" not in again.stderr
    usage = _gwc(cell, "cancel")
    assert usage.returncode != 0 and "Traceback" not in usage.stderr
