"""The operation-entity library against scripted stand-ins for the Lot Server, MSCHED and two WCs.

The stand-ins are real bus members (a private multicast group) that answer as the contracts say,
so these tests pin the library's side of every conversation, its waits and its cleanup, in a few
seconds; tests/e2e/test_lot_*.py run the same library against the real modules.
"""

from __future__ import annotations

import asyncio
import logging
import random
import threading
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc.config import Config
from gwc.ipc.bus import Bus, Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.lot import (OperationEntity, RequestCancelled, RunFailed, Timeouts, read_traveller,
                     verdict)
from tests.conftest import make_config

OK = AckCode.ACK_OK
Handler = Callable[[Conversation, Message], Awaitable[None]]


class FakeCell:
    """ls, msched, wc:m1, wc:m2 on a private bus, each answering with a handler the test may replace."""

    def __init__(self, cfg: Config, url: str, entity: int) -> None:
        self.cfg = cfg
        self.url = url
        self.entity = entity
        self.log = logging.getLogger("fakecell")
        self.seen: list[tuple[str, dict[str, Any]]] = []
        self.run_id = 100
        self.key = 0
        self.complete_runs = True
        self.comp: dict[str, Any] = {}  # how MSCHED ends requests: machine -> (ack_code, note)
        self.loop = asyncio.new_event_loop()
        self.buses: dict[str, Bus] = {}
        self.handlers: dict[str, Handler] = {
            "ENTITY_REQ": self.entity_req, "MACH_REQ": self.mach_req, "CANCEL_RE": self.cancel,
            "UNRESERVE": self.unreserve, "SETUP_RUN": self.setup, "START_RUN": self.start,
        }
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        for name, classes in (("ls", ["ENTITY_REQ"]), ("msched", ["MACH_REQ", "CANCEL_RE", "UNRESERVE"]),
                              ("wc:m1", ["SETUP_RUN", "START_RUN"]), ("wc:m2", ["SETUP_RUN", "START_RUN"])):
            self.buses[name] = asyncio.run_coroutine_threadsafe(self._join(name, classes), self.loop).result(5)

    async def _join(self, name: str, classes: list[str]) -> Bus:
        bus = Bus(name, self.cfg.bus, self.log, classes)
        await bus.sign_on()
        self.loop.create_task(self._serve(bus))
        return bus

    async def _serve(self, bus: Bus) -> None:
        while True:
            conv = await bus.first_message()
            if conv is None or conv.first is None:
                if bus.closed:
                    return
                continue
            m = conv.first.first
            self.seen.append((conv.cls, dict(m.fields)))
            self.loop.create_task(self.handlers[conv.cls](conv, m))

    def close(self) -> None:
        for bus in self.buses.values():
            asyncio.run_coroutine_threadsafe(bus.close(flush=0.2), self.loop).result(5)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)

    def sql(self, text: str, *params: Any) -> None:
        with psycopg.connect(self.url, autocommit=True) as conn:
            conn.execute(text, params)

    def actions(self) -> list[str]:
        return [f["action"] for cls, f in self.seen if cls == "ENTITY_REQ"]

    async def broadcast(self, sender: str, cls: str, msg: Message) -> None:
        conv = await self.buses[sender].start(cls, msg)
        conv.end()

    # ----------------------------------------------------------------- the stand-ins

    async def entity_req(self, conv: Conversation, m: Message) -> None:
        moves = {"import": "waiting_import", "export": "waiting_export", "waiting_machine": "waiting_machine",
                 "running": "running", "completed": "completed", "failed": "failed"}
        state = moves.get(m.action)
        if state:
            self.sql("UPDATE lot_status SET state = %s, reason = %s WHERE entity_id = %s", state, m.reason, m.entity_id)
        await conv.send(message("Entity_Ack", ack_code=OK, lot_id=1, state=state or "created"))
        if m.action in ("import", "export"):  # the operator decides at once
            done = "imported" if m.action == "import" else "exported"
            self.sql("UPDATE lot_status SET state = %s WHERE entity_id = %s", done, m.entity_id)
            await self.broadcast("ls", "LOT_MOVED", message("Lot_Moved", entity_id=m.entity_id, action=m.action,
                                                            lot_id=1))

    async def mach_req(self, conv: Conversation, m: Message) -> None:
        assert conv.first is not None
        machines = [e.machine_id for e in conv.first.messages[1:]]
        self.key += 1
        key = self.key
        await conv.send(message("Machine_Req_Ack", ack_code=OK, request_key=key))
        code, note = self.comp.get(machines[0], (OK, None))
        if code == "wait":
            return  # never ends: the entity's deadline or cleanup must
        await asyncio.sleep(0.05)
        self.run_id += 1
        comp = message("Machine_Req_Comp", ack_code=code, entity_id=m.entity_id, request_key=key, note=note,
                       machine_run_id=self.run_id if code == OK else None, num_machines=len(machines))
        more = [message("Reserved_Machine", machine_id=x) for x in machines] if code == OK else []
        await conv.send(comp, *more)
        await conv.expect("Request_Comp_Ack", timeout=5)

    async def cancel(self, conv: Conversation, m: Message) -> None:
        await conv.send(message("Cancel_Req_Ack", ack_code=AckCode.REQ_KEY_U, cancelled=0))

    async def unreserve(self, conv: Conversation, m: Message) -> None:
        await conv.send(message("Unreserve_Me_Ack", ack_code=OK, freed=1))

    async def setup(self, conv: Conversation, m: Message) -> None:
        code = AckCode.REC_INVAL if m.recipe_id == "bad" else OK
        await conv.send(message("Setup_Run_Ack", ack_code=code))

    async def start(self, conv: Conversation, m: Message) -> None:
        await conv.send(message("Start_Run_Ack", ack_code=OK))
        await asyncio.sleep(0.05)
        wc = f"wc:{m.machine_id}"
        if not self.complete_runs:
            await self.broadcast(wc, "UPD_ME_ST", message("Update_ME_Status", machine_id=m.machine_id,
                                                            status="Shutdown", previous="Running"))
            self.complete_runs = True  # the next try completes
            return
        self.sql("INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) VALUES (%s, %s, 'RESULT', "
                 "'PASS')", m.machine_run_id, m.machine_id)
        await self.broadcast(wc, "RUN_COMPL", message("Run_Complete", machine_id=m.machine_id,
                                                      machine_run_id=m.machine_run_id, ack_code=OK))


@pytest.fixture
def fake(tmp_path: Path, database_url: str) -> Iterator[tuple[FakeCell, OperationEntity]]:
    rnd = random.Random()
    bus = {"group": f"239.255.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}", "port": rnd.randrange(20000, 60000),
           "heartbeat": 0.1, "peer_timeout": 1.0}
    cfg = make_config(tmp_path, database_url, bus=bus)
    with psycopg.connect(database_url, autocommit=True) as conn:
        for mid in ("m1", "m2"):
            conn.execute("INSERT INTO me_config (machine_id, kind) VALUES (%s, 'dummy')", (mid,))
            conn.execute("INSERT INTO machine_status (machine_id, status) VALUES (%s, 'Idle')", (mid,))
            conn.execute("INSERT INTO op_machine_recipe VALUES (%s, 'dummy_recipe', 'dummy_op')", (mid,))
        conn.execute("INSERT INTO lots (lot_id, product_id, script_id) VALUES (1, 'milled_pawn', 'mill_and_measure')")
        conn.execute("INSERT INTO lot_entities (entity_id, lot_id, unit) VALUES (7, 1, 1)")
        conn.execute("INSERT INTO lot_status (entity_id, lot_id, state) VALUES (7, 1, 'created')")
    cell = FakeCell(cfg, database_url, 7)
    log = logging.getLogger("lot-test")
    entity = OperationEntity(cfg, 7, log, Timeouts(answer=3, machines=5, setup=3, run=5, lost_grace=0.2, cleanup=2))
    try:
        yield cell, entity
    finally:
        entity.close()
        cell.close()


def test_a_lot_goes_through_listing_1_with_alternatives(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    cell.comp = {"m1": (AckCode.REQ_CANCEL, "alternative 2 satisfied")}  # MSCHED gave m2, cancelled the sibling
    with entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", [["m1"], ["m2"]])
        assert op.machines == ["m2"] and op.ok and op.passed and op.results == {"RESULT": "PASS"}
        entity.lot_completed("PASS")
        entity.wait_for_export()
    assert cell.actions() == ["attach", "import", "waiting_machine", "running", "completed", "export"]
    reqs = [f for cls, f in cell.seen if cls == "MACH_REQ"]
    assert [(r["op_type"], r["num_machines"]) for r in reqs] == [("dummy_op", 1), ("dummy_op", 1)]
    assert [cls for cls, _ in cell.seen if cls in ("SETUP_RUN", "START_RUN", "UNRESERVE")] == \
        ["SETUP_RUN", "START_RUN", "UNRESERVE"]
    trav = read_traveller(entity.cfg, 7)
    assert trav and trav["steps"][0]["machines"] == ["m2"] and trav["result"] == "PASS"


def test_an_exception_in_the_script_cancels_unreserves_and_fails_the_entity(fake: tuple[FakeCell, OperationEntity]
                                                                            ) -> None:
    cell, entity = fake
    with pytest.raises(ZeroDivisionError), entity:
        entity.wait_for_import()
        1 / 0
    classes = [cls for cls, _ in cell.seen]
    assert "CANCEL_RE" in classes and "UNRESERVE" in classes
    failed = [f for cls, f in cell.seen if cls == "ENTITY_REQ" and f["action"] == "failed"]
    assert failed and "ZeroDivisionError" in failed[0]["reason"]


def test_a_cancelled_request_reaches_the_lot_as_req_cancel(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    cell.comp = {"m1": (AckCode.REQ_CANCEL, "cancelled by hi:root")}
    with pytest.raises(RequestCancelled, match="REQ_CANCEL"), entity:
        entity.wait_for_import()
        entity.operate("dummy_op", [["m1"]])
    failed = [f for cls, f in cell.seen if cls == "ENTITY_REQ" and f["action"] == "failed"]
    assert "REQ_CANCEL" in failed[0]["reason"]


def test_a_machine_lost_mid_run_is_given_back_and_the_operation_asked_again(fake: tuple[FakeCell, OperationEntity]
                                                                           ) -> None:
    cell, entity = fake
    cell.complete_runs = False  # the first run's machine shuts down instead of completing
    with entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", [["m1"]])
        assert op.tries == 2 and op.ok
        entity.lot_completed("PASS")
    unreserves = [cls for cls, _ in cell.seen if cls == "UNRESERVE"]
    assert len(unreserves) == 2
    notes = [s["note"] for s in read_traveller(entity.cfg, 7)["steps"]]  # type: ignore[index]
    assert notes[0].startswith("machine lost") and notes[1] == "within tolerance"


def test_a_refused_setup_fails_the_lot_with_the_machines_answer(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    with pytest.raises(RunFailed, match="Rec_Inval"), entity:
        entity.wait_for_import()
        entity.operate("dummy_op", [["m1"]], recipes="bad")


def test_waiting_for_machines_has_a_deadline(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    cell.comp = {"m1": ("wait", None)}
    entity.timeouts = Timeouts(answer=3, machines=0.5, cleanup=2)
    with pytest.raises(Exception, match="timed out"), entity:
        entity.wait_for_import()
        entity.operate("dummy_op", [["m1"]])
    assert "CANCEL_RE" in [cls for cls, _ in cell.seen]


@pytest.mark.parametrize("results, ok", [
    ({"RESULT": "PASS"}, True),
    ({"RESULT": "FAIL"}, False),
    ({"RESULT": "NONE"}, False),
    ({}, False),
    ({"RESULT": "PASS", "PARTS": "1"}, True),
    ({"king": "PASS", "queen": "FAIL"}, False),
    ({"deviation": "0.03", "tolerance": "0.05"}, True),
    ({"deviation": "-0.08", "tolerance": "0.05"}, False),
    ({"DIAMETER": "25.02", "DIAMETER_nominal": "25", "DIAMETER_tol": "0.05"}, True),
    ({"DIAMETER": "25.2", "DIAMETER_nominal": "25", "DIAMETER_tol": "0.05"}, False),
])
def test_verdict_reads_pass_fail_and_measured_tolerances(results: dict[str, str], ok: bool) -> None:
    assert verdict(results)[0] is ok


def test_a_second_alternative_bound_too_is_given_back(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake  # this MSCHED binds both alternatives: the entity keeps one, frees the other
    with entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", [["m1"], ["m2"]])
        entity.lot_completed("PASS")
    spare = ({"m1", "m2"} - set(op.machines)).pop()
    freed = [f.get("machine_id") for cls, f in cell.seen if cls == "UNRESERVE"]
    assert spare in freed, freed
