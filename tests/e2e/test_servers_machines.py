"""The servers with real machines (issue 6): WC and ME processes, MSCHED, every server.

A machine whose WC and ME are killed together (kill -9) is seen by the Machine Server's liveness
watch; a recipe file edited after approval is refused at SETUP_RUN; an alarm a WC raises holds the
WC until the operator clears it."""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any

import pytest

from gwc.cell import startup
from gwc.ipc import Batch, BlockingConversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.servers.recipe import version_path
from tests.e2e.test_servers import ask, ears, q1  # noqa: F401 (ears is a fixture)
from tests.harness import CellHarness, wait_for

OK = AckCode.ACK_OK
T = 20.0


class Request:
    """One MACH_REQ conversation, played as a lot entity plays it (CONTRACTS.md)."""

    def __init__(self, cell: CellHarness, entity: int, machine: str) -> None:
        self.entity = entity
        self.conv: BlockingConversation
        self.conv, batch = cell.bus.request(
            "MACH_REQ",
            message("Machine_Request", entity_id=entity, op_type="dummy_op", num_machines=1),
            message("Machine_Entry", machine_id=machine),
            to="msched",
            timeout=T,
        )
        self.ack = batch.first
        assert self.ack.ack_code == OK, self.ack
        self.done: Batch | None = None

    def comp(self) -> Message:
        """The Machine_Req_Comp, acknowledged."""
        self.done = self.conv.expect("Machine_Req_Comp", timeout=T)
        self.conv.send(message("Request_Comp_Ack", entity_id=self.entity, ack_code=OK))
        self.conv.end()
        return self.done.first

    @property
    def reserved(self) -> list[str]:
        assert self.done is not None
        return [m.machine_id for m in self.done.messages[1:]]


def entities(cell: CellHarness, n: int) -> list[int]:
    """n lot entities from the Lot Server, imported (MSCHED serves entities in the cell)."""
    made = ask(cell.bus, "CREATE_LOT", message("Create_Lot_Entity", product_id="milled_pawn", quantity=n), "ls")
    assert made.ack_code == OK, made
    for e in made.entity_ids:
        assert ask(cell.bus, "ENTITY_REQ", message("Entity_Request", entity_id=e, action="import"), "ls").ack_code == OK
        assert (
            ask(cell.bus, "IMPORT_LOT", message("Lot_Decision", entity_id=e, action="import", by="op"), "ls").ack_code
            == OK
        )
    return list(made.entity_ids)


def machine_cell(make_cell: Any, run_time: float, *machines: str, **options: Any) -> CellHarness:
    cell = make_cell(machines=[{"id": m, "kind": "dummy", "run_time": run_time, **options} for m in machines])
    cell.start_servers("cas", "ers", "ms", "ls", "sls", "msched")
    for m in machines:
        cell.start_machine_processes(m)
    return cell


def me_start(cell: CellHarness, machine: str) -> None:
    assert startup(cell.bus, f"wc:{machine}", "ME_START", timeout=T) == "started"


def bound(cell: CellHarness, entity: int, machine: str) -> int:
    """Reserve a free machine for an entity; its machine_run_id."""
    req = Request(cell, entity, machine)
    comp = req.comp()
    assert comp.ack_code == OK and req.reserved == [machine], comp
    return int(comp.machine_run_id)


def setup_run(cell: CellHarness, machine: str, run_id: int, entity: int) -> Message:
    return ask(
        cell.bus,
        "SETUP_RUN",
        message(
            "Setup_Run",
            machine_id=machine,
            recipe_id="dummy_recipe",
            op_type="dummy_op",
            machine_run_id=run_id,
            entity_id=entity,
        ),
        f"wc:{machine}",
        timeout=T,
    )


def start_run(cell: CellHarness, machine: str, run_id: int) -> Message:
    return ask(
        cell.bus,
        "START_RUN",
        message("Start_Run", machine_id=machine, machine_run_id=run_id),
        f"wc:{machine}",
        timeout=T,
    )


@pytest.mark.parametrize("when", ["Idle", "Running"])
def test_kill_9_of_a_machine_pair_is_seen_and_a_waiting_lot_gets_its_alternative(
    make_cell: Any, ears: Any, when: str
) -> None:
    cell = machine_cell(make_cell, 60.0, "wc1", "wc2")
    ear = ears(cell, f"ear.{cell.tag}", "UPD_ME_ST")
    me_start(cell, "wc1")
    me_start(cell, "wc2")
    holder, waiter, other = entities(cell, 3)
    run_id = bound(cell, holder, "wc1")  # wc1 is taken: the waiter's first choice must wait
    bound(cell, other, "wc2")  # and so is its alternative, for now
    Request(cell, waiter, "wc1")
    alternative = Request(cell, waiter, "wc2")
    if when == "Running":
        assert setup_run(cell, "wc1", run_id, holder).ack_code == OK
        assert start_run(cell, "wc1", run_id).ack_code == OK
    assert q1(cell, "select status from machine_status where machine_id = 'wc1'") == (when,)

    pids = [cell.pid("wc", "wc1"), cell.pid("me", "wc1")]
    killed = time.monotonic()
    for pid in pids:
        os.kill(pid, signal.SIGKILL)
    wait_for(
        lambda: q1(cell, "select status from machine_status where machine_id = 'wc1'") == ("Shutdown",),
        10,
        "MACHINE_STATUS of wc1 to say Shutdown",
    )
    assert time.monotonic() - killed < 5.0, f"seen after {time.monotonic() - killed:.1f}s"
    assert not cell.alive("wc", "wc1") and not cell.alive("me", "wc1")
    wait_for(
        lambda: q1(
            cell,
            "select alarm_no from alarms where alarm_id = 'WC_SILENT' and machine_id = 'wc1' and cleared_at is null",
        ),
        5,
        "alarm WC_SILENT pending",
    )
    told = ear.wait("Update_ME_Status wc1 Shutdown", lambda c, m: m.machine_id == "wc1" and m.status == "Shutdown")
    assert told.previous == when
    wait_for(lambda: cell.log_has("msched", "machine wc1 shut down"), 5, "MSCHED to act on the Shutdown")
    assert "msched" in ear.bus.peers() and "UPD_ME_ST" in ear.bus.peers()["msched"].interest
    # the alternative: wc2 is freed, and the waiting lot gets it
    assert ask(cell.bus, "UNRESERVE", message("Unreserve_Me", entity_id=other, by="test"), "msched").ack_code == OK
    comp = alternative.comp()
    assert comp.ack_code == OK and alternative.reserved == ["wc2"], comp
    assert q1(cell, "select status from machine_status where machine_id = 'wc2'") == ("Idle",)


def test_recipe_file_changed_after_approval_is_refused_until_approved_again(make_cell: Any, ears: Any) -> None:
    cell = machine_cell(make_cell, 0.1, "wc1")
    ear = ears(cell, f"ear.{cell.tag}", "RUN_COMPL")
    me_start(cell, "wc1")
    (e,) = entities(cell, 1)
    run_id = bound(cell, e, "wc1")
    path = version_path(cell.cfg, "dummy_recipe", 1)
    wait_for(path.exists, 5, "the recipe library file")
    path.write_text(path.read_text() + "SPEED 11\n")  # edited on disk after its approval
    refused = setup_run(cell, "wc1", run_id, e)
    assert refused.ack_code == AckCode.REC_INVAL, refused
    wait_for(
        lambda: q1(cell, "select alarm_text from alarms where alarm_id = 'REC_INVAL' and machine_id = 'wc1'"),
        5,
        "alarm REC_INVAL",
    )
    assert q1(cell, "select status from machine_status where machine_id = 'wc1'") == ("Idle",)
    again = ask(cell.bus, "RECIPE_APPR", message("Recipe_Approve", recipe_id="dummy_recipe", by="op"), "ers")
    assert (again.ack_code, again.version) == (OK, 2)
    assert setup_run(cell, "wc1", run_id, e).ack_code == OK
    assert start_run(cell, "wc1", run_id).ack_code == OK
    done = ear.wait("Run_Complete", lambda c, m: m.machine_run_id == run_id, timeout=T)
    assert done.ack_code == OK
    wait_for(
        lambda: q1(cell, "select runs_since_maintenance from machine_status where machine_id = 'wc1'") == (1,),
        5,
        "the Machine Server to count the run",
    )


def test_wc_alarm_is_pending_and_shown_and_the_wc_continues_only_once_cleared(make_cell: Any) -> None:
    cell = machine_cell(make_cell, 0.1, "wc1", homing_alarm=True)
    outcome: dict[str, Any] = {}

    def go() -> None:
        try:
            outcome["ok"] = startup(cell.bus, "wc:wc1", "ME_START", timeout=T + 10)
        except Exception as e:  # reported below
            outcome["error"] = e

    starting = threading.Thread(target=go)
    starting.start()
    try:
        no = wait_for(
            lambda: q1(
                cell,
                "select alarm_no from alarms where alarm_id = 'HOME_CMM' and machine_id = 'wc1' and cleared_at is null",
            ),
            T,
            "alarm HOME_CMM pending in CAS",
        )[0]
        line = ask(cell.bus, "STATUS_LN", message("Status_Line_Get"), "sls")
        assert line.alarms == 1 and f"#{no}" in line.text and "Push the start button" in line.text
        assert starting.is_alive() and not outcome  # the WC holds its startup for the operator
        assert q1(cell, "select status from machine_status where machine_id = 'wc1'") == ("Shutdown",)
        assert (
            ask(cell.bus, "ALARM_CLR_REQ", message("Alarm_Clear_Request", alarm_no=no, cleared_by="op"), "cas").ack_code
            == OK
        )
    finally:
        starting.join(T + 15)
    assert outcome.get("ok") == "started", outcome
    assert q1(cell, "select status from machine_status where machine_id = 'wc1'") == ("Idle",)
    assert ask(cell.bus, "STATUS_LN", message("Status_Line_Get"), "sls").alarms == 0
