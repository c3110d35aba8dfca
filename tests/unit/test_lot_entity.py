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
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc.config import Config
from gwc.ipc.bus import Bus, Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.conversation import Peer
from gwc.lot import (
    LotError,
    LotTimeout,
    MachineLost,
    Operation,
    OperationEntity,
    RequestCancelled,
    RunFailed,
    RunInDoubt,
    Timeouts,
    read_traveller,
    verdict,
)
from gwc.module import NOT_STARTED
from tests.conftest import make_config
from tests.harness import wait_for

OK = AckCode.ACK_OK
Handler = Callable[[Conversation, Message], Awaitable[None]]


def one_lot(entity: OperationEntity, alternatives: list[list[str]]) -> Operation:
    """The whole life of a lot of one operation: imported, the operation, completed (PASS)."""
    with entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", alternatives)
        entity.lot_completed("PASS")
    return op


class FakeCell:
    """ls, msched, wc:m1, wc:m2 on a private bus, each answering with a handler the test may replace."""

    def __init__(self, cfg: Config, url: str, entity: int) -> None:
        self.cfg = cfg
        self.url = url
        self.entity = entity
        self.log = logging.getLogger("fakecell")
        self.seen: list[tuple[str, dict[str, Any]]] = []
        self.at: list[float] = []  # when each of `seen` came (monotonic)
        self.run_id = 100
        self.key = 0
        self.complete_runs = True  # False: the next run's ME dies (its agent says so) and the machine shuts down
        self.inline: dict[str, str] | None = None  # the results a Run_Complete carries (None: only the table's)
        self.lose_run: list[tuple[str, int | None]] = []  # instead of completing the next run: these UPD_ME_ST
        self.comp: dict[str, Any] = {}  # how MSCHED ends requests: machine -> (ack_code, note)
        self.ack: dict[str, Any] = {}  # how MSCHED answers requests at once: machine -> (ack_code, note)
        self.queued: dict[int, tuple[Conversation, Message, list[str]]] = {}  # requests left waiting ("wait")
        self.loop = asyncio.new_event_loop()
        self.buses: dict[str, Bus] = {}
        self.handlers: dict[str, Handler] = {
            "ENTITY_REQ": self.entity_req,
            "MACH_REQ": self.mach_req,
            "CANCEL_RE": self.cancel,
            "UNRESERVE": self.unreserve,
            "SETUP_RUN": self.setup,
            "START_RUN": self.start,
        }
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.classes = {
            "ls": ["ENTITY_REQ"],
            "msched": ["MACH_REQ", "CANCEL_RE", "UNRESERVE"],
            "wc:m1": ["SETUP_RUN", "START_RUN"],
            "wc:m2": ["SETUP_RUN", "START_RUN"],
        }
        for name in self.classes:
            self.join(name)

    def join(self, name: str) -> None:
        """`name` (back) on the bus."""
        self.buses[name] = asyncio.run_coroutine_threadsafe(self._join(name, self.classes[name]), self.loop).result(5)

    def leave(self, name: str) -> None:
        """`name` leaves the bus (a clean close: its peers know at once)."""
        asyncio.run_coroutine_threadsafe(self.buses.pop(name).close(flush=0.2), self.loop).result(5)

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
            self.at.append(time.monotonic())
            start = conv.cls == "SETUP_RUN" and m.start
            self.loop.create_task(self._setup_and_start(conv, m) if start else self.handlers[conv.cls](conv, m))

    async def _setup_and_start(self, conv: Conversation, m: Message) -> None:
        """A SETUP_RUN that also starts its run, as a WC serves it: the test's SETUP_RUN handler, then (set
        up) its START_RUN handler, seen as a START_RUN `with_setup`; one Setup_Run_Ack answers both."""
        setup = await self._answer_of("SETUP_RUN", m)
        if setup is None or setup.ack_code != OK:
            if setup is not None:
                await conv.send(setup)
            return
        self.seen.append(("START_RUN", {**m.fields, "with_setup": True}))
        self.at.append(time.monotonic())
        started = await self._answer_of("START_RUN", m)
        if started is not None:
            await conv.send(
                message("Setup_Run_Ack", ack_code=started.ack_code, note=started.note, recipe_id=setup.recipe_id)
            )

    async def _answer_of(self, cls: str, m: Message) -> Message | None:
        """What the test's handler of `cls` answers m (None: nothing), the rest of its work left running."""
        answered: asyncio.Future[Message] = self.loop.create_future()

        class Kept:
            async def send(self, msg: Message) -> None:
                if not answered.done():
                    answered.set_result(msg)

        work = self.loop.create_task(self.handlers[cls](Kept(), m))  # type: ignore[arg-type]
        await asyncio.wait({answered, work}, return_when=asyncio.FIRST_COMPLETED)
        return answered.result() if answered.done() else None

    def close(self) -> None:
        for bus in self.buses.values():
            asyncio.run_coroutine_threadsafe(bus.close(flush=0.2), self.loop).result(5)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()  # its self-pipe sockets, else left open (the leak check finds them)

    def sql(self, text: str, *params: Any) -> Any:
        """Run one statement; its first row, if it returns any."""
        with psycopg.connect(self.url, autocommit=True) as conn:
            cur = conn.execute(text, params)
            return cur.fetchone() if cur.description else None

    def actions(self) -> list[str]:
        return [f["action"] for cls, f in self.seen if cls == "ENTITY_REQ"]

    def when(self, cls: str) -> list[float]:
        return [t for (c, _), t in zip(self.seen, self.at) if c == cls]

    def later(self, delay: float, fn: Callable[[], Any]) -> None:
        """Run fn (blocking is fine: a thread of its own) `delay` s from now."""
        timer = threading.Timer(delay, fn)
        timer.daemon = True
        timer.start()

    def store_pass(self, machine: str, run: int) -> None:
        """What a WC stores for a run that passed: its result and its outcome."""
        self.sql(
            "INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) "
            "VALUES (%s, %s, 'RESULT', 'PASS')",
            run,
            machine,
        )
        self.sql(
            "INSERT INTO machine_run_outcome (machine_run_id, machine_id, ack_code) VALUES (%s, %s, 'ACK_OK')",
            run,
            machine,
        )

    def status(self, machine: str, status: str, run: int | None = None) -> None:
        """The Machine Server's table: machine's status (and run) now."""
        self.sql(
            "UPDATE machine_status SET status = %s, machine_run_id = coalesce(%s, machine_run_id) "
            "WHERE machine_id = %s",
            status,
            run,
            machine,
        )

    async def broadcast(self, sender: str, cls: str, msg: Message, to: str | None = None) -> None:
        conv = await self.buses[sender].start(cls, msg, to=to)
        conv.end()

    # ----------------------------------------------------------------- the stand-ins

    async def entity_req(self, conv: Conversation, m: Message) -> None:
        moves = {
            "import": "waiting_import",
            "export": "waiting_export",
            "waiting_machine": "waiting_machine",
            "running": "running",
            "completed": "completed",
            "failed": "failed",
            "held": "held",
        }
        state = moves.get(m.action)
        if state:
            self.sql("UPDATE lot_status SET state = %s, reason = %s WHERE entity_id = %s", state, m.reason, m.entity_id)
        else:  # attach, state: as the table has it
            state = self.sql("SELECT state FROM lot_status WHERE entity_id = %s", m.entity_id)[0]
        await conv.send(message("Entity_Ack", ack_code=OK, lot_id=1, state=state))
        if m.action in ("import", "export"):  # the operator decides at once
            done = "imported" if m.action == "import" else "exported"
            self.sql("UPDATE lot_status SET state = %s WHERE entity_id = %s", done, m.entity_id)
            await self.broadcast(  # to the entity's script, as the Lot Server tells it
                "ls",
                "LOT_MOVED",
                message("Lot_Moved", entity_id=m.entity_id, action=m.action, lot_id=1),
                to=f"lot:{m.entity_id}",
            )

    async def mach_req(self, conv: Conversation, m: Message) -> None:
        assert conv.first is not None
        machines = [e.machine_id for e in conv.first.messages[1:]]
        self.key += 1
        key = self.key
        code, note = self.ack.get(machines[0], (OK, None))
        if code != OK:
            await conv.send(message("Machine_Req_Ack", ack_code=code, note=note))
            return
        await conv.send(message("Machine_Req_Ack", ack_code=OK, request_key=key))
        code, note = self.comp.get(machines[0], (OK, None))
        if code == "wait":
            self.queued[key] = (conv, m, machines)  # ends when cancelled, or never
            return
        await asyncio.sleep(0.05)
        self.run_id += 1
        comp = message(
            "Machine_Req_Comp",
            ack_code=code,
            entity_id=m.entity_id,
            request_key=key,
            note=note,
            machine_run_id=self.run_id if code == OK else None,
            num_machines=len(machines),
        )
        more = [message("Reserved_Machine", machine_id=x) for x in machines] if code == OK else []
        await conv.send(comp, *more)
        await conv.expect("Request_Comp_Ack", timeout=5)

    async def cancel(self, conv: Conversation, m: Message) -> None:
        ended = [
            k
            for k, (_, req, _) in self.queued.items()
            if k == m.request_key or (m.request_key is None and req.entity_id == m.entity_id)
        ]
        for k in ended:
            req_conv, req, machines = self.queued.pop(k)
            await req_conv.send(
                message(
                    "Machine_Req_Comp",
                    ack_code=AckCode.REQ_CANCEL,
                    entity_id=req.entity_id,
                    request_key=k,
                    note=f"cancelled by {m.by}",
                    num_machines=len(machines),
                )
            )
        await conv.send(message("Cancel_Req_Ack", ack_code=OK if ended else AckCode.REQ_KEY_U, cancelled=len(ended)))

    async def unreserve(self, conv: Conversation, m: Message) -> None:
        await conv.send(message("Unreserve_Me_Ack", ack_code=OK, freed=1))

    async def setup(self, conv: Conversation, m: Message) -> None:
        code = AckCode.REC_INVAL if m.recipe_id == "bad" else OK
        await conv.send(message("Setup_Run_Ack", ack_code=code, recipe_id=m.recipe_id or "dummy_recipe"))

    async def start(self, conv: Conversation, m: Message) -> None:
        self.status(m.machine_id, "Running", m.machine_run_id)
        await conv.send(message("Start_Run_Ack", ack_code=OK))
        await asyncio.sleep(0.05)
        wc = f"wc:{m.machine_id}"
        if self.lose_run:
            changes, self.lose_run = self.lose_run, []  # the next try completes
            for status, run in changes:
                await self.broadcast(
                    wc,
                    "UPD_ME_ST",
                    message("Update_ME_Status", machine_id=m.machine_id, status=status, machine_run_id=run),
                )
            return
        if not self.complete_runs:
            died = message(
                "Module_Died",
                module=f"me:{m.machine_id}",
                host="agent:test",
                how="killed by SIGKILL",
                state="BACKOFF",
                restarts=0,
                restart_in=0.0,
            )
            await self.broadcast(wc, "MOD_DIED", died)
            await self.broadcast(
                wc,
                "UPD_ME_ST",
                message("Update_ME_Status", machine_id=m.machine_id, status="Shutdown", previous="Running"),
            )
            self.complete_runs = True  # the next try completes
            return
        self.sql(
            "INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) VALUES (%s, %s, 'RESULT', "
            "'PASS')",
            m.machine_run_id,
            m.machine_id,
        )
        self.status(m.machine_id, "Idle")
        await self.broadcast(
            wc,
            "RUN_COMPL",
            message(
                "Run_Complete",
                machine_id=m.machine_id,
                machine_run_id=m.machine_run_id,
                ack_code=OK,
                results=self.inline,
            ),
        )


@pytest.fixture
def fake(tmp_path: Path, database_url: str) -> Iterator[tuple[FakeCell, OperationEntity]]:
    rnd = random.Random()
    bus = {
        "group": f"239.255.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}",
        "port": rnd.randrange(20000, 60000),
        "heartbeat": 0.1,
        "peer_timeout": 1.0,
    }
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
    entity = OperationEntity(
        cfg,
        7,
        log,
        Timeouts(
            answer=3,
            machines=5,
            setup=3,
            run=5,
            lost_grace=0.2,
            cleanup=2,
            retry=3,
            backoff=0.05,
            backoff_max=0.2,
            pause=0.1,
        ),
    )
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
    assert [cls for cls, _ in cell.seen if cls in ("SETUP_RUN", "START_RUN", "UNRESERVE")] == [
        "SETUP_RUN",
        "START_RUN",
        "UNRESERVE",
    ]
    setup, start = (f for cls, f in cell.seen if cls in ("SETUP_RUN", "START_RUN"))
    assert setup["start"] and start["with_setup"], "started by its SETUP_RUN: no START_RUN round trip"
    trav = read_traveller(entity.cfg, 7)
    assert trav and trav["steps"][0]["machines"] == ["m2"] and trav["result"] == "PASS"


def test_a_runs_results_that_came_with_its_run_complete_are_not_read_again(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    # The table holds RESULT only: what the lot reports can have come only from the Run_Complete.
    cell, entity = fake
    cell.inline = {"RESULT": "PASS", "LENGTH": "31.98"}
    with entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", [["m1"]])
        assert op.ok and op.results == {"LENGTH": "31.98", "RESULT": "PASS"}
        entity.lot_completed("PASS")
        entity.wait_for_export()


def test_an_exception_in_the_script_cancels_unreserves_and_fails_the_entity(
    fake: tuple[FakeCell, OperationEntity],
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


def test_a_machine_whose_me_died_mid_run_is_given_back_and_the_operation_asked_again_at_once(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=5, setup=3, run=60, lost_grace=3, pause=5)
    cell.complete_runs = False  # the first run's ME dies, announced by its agent, and the machine shuts down
    with entity:
        entity.wait_for_import()
        t0 = time.monotonic()
        op = entity.operate("dummy_op", [["m1"]])
        took = time.monotonic() - t0
        assert op.tries == 2 and op.ok
        assert took < 2.0, f"a known death waits neither lost_grace (3 s) nor the pause (5 s): {took:.1f}s"
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
    entity.timeouts = Timeouts(answer=3, machines=0.5, cleanup=2, retry=3)
    with pytest.raises(Exception, match="timed out"), entity:
        entity.wait_for_import()
        entity.operate("dummy_op", [["m1"]])
    assert "CANCEL_RE" in [cls for cls, _ in cell.seen]


@pytest.mark.parametrize(
    "results, ok",
    [
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
    ],
)
def test_verdict_reads_pass_fail_and_measured_tolerances(results: dict[str, str], ok: bool) -> None:
    assert verdict(results)[0] is ok


def test_a_second_alternative_bound_too_is_given_back(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake  # this MSCHED binds both alternatives: the entity keeps one, frees the other
    op = one_lot(entity, [["m1"], ["m2"]])
    spare = ({"m1", "m2"} - set(op.machines)).pop()
    freed = [f.get("machine_id") for cls, f in cell.seen if cls == "UNRESERVE"]
    assert spare in freed, freed


# ----------------------------------------------------------------- machines that go away (soak BUG-1, 3, 4)


def test_a_wc_first_heard_after_its_run_began_is_the_runs_and_its_restart_loses_the_run(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    # A WC leaves a lot's query to its beat: a lot bound at once may set up on a WC it has not heard of.
    _, entity = fake
    with entity.heard.cond:
        entity.heard.peer_inc.pop("wc:m1", None)
        entity.heard.began[("m1", 5)] = (time.monotonic(), None)
    assert entity.heard.lost("m1", 5) is None  # not heard of yet, within lost_grace
    entity.heard.peer_changed("wc:m1", Peer("wc:m1", 7, frozenset(), time.monotonic()))
    assert entity.heard.lost("m1", 5) is None  # heard of: the run's WC
    entity.heard.peer_changed("wc:m1", Peer("wc:m1", 8, frozenset(), time.monotonic()))
    assert entity.heard.lost("m1", 5) == "wc:m1 restarted"


@pytest.mark.parametrize(
    "changes, table",
    [
        # killed and restarted within lost_grace: only the UPD_ME_ST tell, the table shows nothing wrong
        ([("Shutdown", 101), ("Idle", 101)], ("Running", 101)),
        # no broadcast came at all: MACHINE_STATUS says the machine is Idle on another run
        ([("Running", 101)], ("Idle", 99)),
    ],
    ids=["restarted", "idle-in-the-table"],
)
def test_a_machine_that_lost_its_run_is_not_waited_for_even_when_it_is_up_again(
    fake: tuple[FakeCell, OperationEntity], changes: list[tuple[str, int]], table: tuple[str, int]
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=5, setup=3, run=60, lost_grace=0.2, cleanup=2, retry=3, pause=0.1)
    cell.lose_run = changes

    async def start(conv: Conversation, m: Message) -> None:
        await FakeCell.start(cell, conv, m)
        if m.machine_run_id == 101:
            cell.status(m.machine_id, *table)

    cell.handlers["START_RUN"] = start
    t0 = time.monotonic()
    op = one_lot(entity, [["m1"]])
    assert op.tries == 2 and op.ok and op.machine_run_id == 102
    assert time.monotonic() - t0 < 10  # not Timeouts.run (60 s)
    notes = [s["note"] for s in read_traveller(entity.cfg, 7)["steps"]]  # type: ignore[index]
    assert notes[0].startswith("machine lost: m1 went") and "run 101" in notes[0], notes


def test_a_run_whose_run_compl_never_came_counts_from_the_outcome_its_wc_stored(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    cell.lose_run = [("Idle", 101)]  # the machine went Idle on our run; its RUN_COMPL never came

    async def start(conv: Conversation, m: Message) -> None:  # what the WC stored before it went Idle
        cell.store_pass(m.machine_id, m.machine_run_id)
        await FakeCell.start(cell, conv, m)

    cell.handlers["START_RUN"] = start
    op = one_lot(entity, [["m1"]])
    assert op.tries == 1 and op.ok and op.machine_run_id == 101 and op.results == {"RESULT": "PASS"}


def test_setup_gives_up_as_soon_as_the_machine_shuts_down_and_asks_again_once_it_is_up(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=10, setup=60, run=5, lost_grace=0.2, cleanup=2, retry=3, pause=0.1)
    setups = 0

    async def setup(conv: Conversation, m: Message) -> None:
        nonlocal setups
        setups += 1
        if setups > 1:
            return await FakeCell.setup(cell, conv, m)
        # The WC was killed -9: no answer ever; the Machine Server marks the machine Shutdown, and the
        # operator brings it back a moment later.
        await asyncio.sleep(0.2)
        cell.status("m1", "Shutdown")
        await cell.broadcast(
            "wc:m2", "UPD_ME_ST", message("Update_ME_Status", machine_id="m1", status="Shutdown", previous="Idle")
        )
        cell.later(0.6, lambda: cell.status("m1", "Idle"))

    cell.handlers["SETUP_RUN"] = setup
    t0 = time.monotonic()
    op = one_lot(entity, [["m1"]])
    assert op.tries == 2 and op.ok
    assert time.monotonic() - t0 < 10  # not Timeouts.setup (60 s)
    first, second = cell.when("SETUP_RUN")
    assert second - first > 0.6  # asked again only once m1 was up again
    assert len(cell.when("UNRESERVE")) == 2


def test_setup_gives_up_when_the_wc_leaves_the_bus(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, setup=60, lost_grace=0.3, cleanup=2, retry=1)

    async def silent(conv: Conversation, m: Message) -> None:
        cell.later(0.2, lambda: cell.leave("wc:m1"))

    cell.handlers["SETUP_RUN"] = silent
    t0 = time.monotonic()
    with pytest.raises(MachineLost, match="wc:m1 is not on the bus"), entity:
        entity.setup_run("m1", "dummy_recipe", "dummy_op", 55)
    assert time.monotonic() - t0 < 10


def test_a_machine_refusing_a_setup_is_asked_again_after_a_pause_once_it_is_up(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=10, setup=3, run=5, lost_grace=0.2, cleanup=2, retry=3, pause=0.3)
    setups = 0

    async def setup(conv: Conversation, m: Message) -> None:
        nonlocal setups
        setups += 1
        if setups > 1:
            return await FakeCell.setup(cell, conv, m)
        cell.status("m1", "Shutdown")  # its ME stopped: the machine is going down
        cell.later(0.5, lambda: cell.status("m1", "Idle"))
        await conv.send(
            message(
                "Setup_Run_Ack",
                ack_code=AckCode.START_FAIL,
                note="ME refused the setup: cannot set up a run: the machine is shutdown",
            )
        )

    cell.handlers["SETUP_RUN"] = setup
    op = one_lot(entity, [["m1"]])
    assert op.tries == 2 and op.ok
    first, second = cell.when("SETUP_RUN")
    assert second - first >= 0.5  # the pause, then m1 up again: not three tries in 150 ms


# ----------------------------------------------------------------- servers that restart (soak BUG-2)


def test_the_lot_server_and_msched_are_asked_again_while_not_started_silent_or_without_database(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(
        answer=0.5, machines=5, setup=3, run=5, lost_grace=0.2, cleanup=2, retry=10, backoff=0.05, backoff_max=0.2
    )
    attaches = unreserves = requests = 0

    async def entity_req(conv: Conversation, m: Message) -> None:
        nonlocal attaches
        if m.action == "attach":
            attaches += 1
            if attaches == 1:  # just restarted, STARTUP not yet done
                return await conv.send(message("Entity_Ack", ack_code=AckCode.NOTNOW, note=NOT_STARTED))
            if attaches == 2:  # busy or dying: no answer
                return
        await FakeCell.entity_req(cell, conv, m)

    async def mach_req(conv: Conversation, m: Message) -> None:
        nonlocal requests
        requests += 1
        if requests == 1:  # its database is away: nothing was queued
            return await conv.send(message("Machine_Req_Ack", ack_code=AckCode.DB_BADREA, note="database away"))
        await FakeCell.mach_req(cell, conv, m)

    async def unreserve(conv: Conversation, m: Message) -> None:
        nonlocal unreserves
        unreserves += 1
        if unreserves == 1:
            return await conv.send(message("Unreserve_Me_Ack", ack_code=AckCode.NOTNOW, note=NOT_STARTED))
        if unreserves == 2:
            return await conv.send(message("Unreserve_Me_Ack", ack_code=AckCode.DB_BADREA, note="database away"))
        await FakeCell.unreserve(cell, conv, m)

    cell.handlers["ENTITY_REQ"] = entity_req
    cell.handlers["MACH_REQ"] = mach_req
    cell.handlers["UNRESERVE"] = unreserve
    op = one_lot(entity, [["m1"]])
    assert op.ok and attaches == 3 and requests == 2 and unreserves == 3
    assert cell.actions()[:3] == ["attach", "attach", "attach"] and cell.actions()[-1] == "completed"


def test_a_script_started_while_the_lot_server_is_down_attaches_once_it_is_back(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, cleanup=2, retry=10, backoff=0.05, backoff_max=0.2)
    cell.leave("ls")
    cell.later(0.5, lambda: cell.join("ls"))
    with entity:
        assert cell.actions() == ["attach"]
        entity.lot_completed("PASS")
    assert cell.actions() == ["attach", "completed"]


def test_a_server_that_never_starts_fails_the_step_after_the_retry_window(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, cleanup=2, retry=0.6, backoff=0.05, backoff_max=0.2)

    async def not_started(conv: Conversation, m: Message) -> None:
        await conv.send(message("Entity_Ack", ack_code=AckCode.NOTNOW, note=NOT_STARTED))

    cell.handlers["ENTITY_REQ"] = not_started
    t0 = time.monotonic()
    with pytest.raises(LotTimeout, match=r"ls cannot answer now \(Notnow module not started\)"), entity:
        pass
    assert 0.6 <= time.monotonic() - t0 < 10
    assert cell.actions().count("attach") >= 3


# ----------------------------------------------------------------- alternatives (soak BUG-6)


def test_alternatives_share_an_alt_group_and_a_late_sibling_refused_is_a_sibling_cancel(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    cell.ack = {"m1": (AckCode.REQ_CANCEL, "alternative of a group already bound")}  # came after m2 was bound
    with entity:
        entity.wait_for_import()
        first = entity.operate("dummy_op", [["m1"], ["m2"]])
        second = entity.operate("dummy_op", [["m1"], ["m2"]])
        entity.lot_completed("PASS")
    assert first.machines == second.machines == ["m2"]
    groups = [f["alt_group"] for cls, f in cell.seen if cls == "MACH_REQ"]
    assert len(groups) == 4 and all(groups)
    assert groups[0] == groups[1] != groups[2] == groups[3]


def test_no_request_is_left_queued_for_a_finished_entity(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    cell.comp = {"m1": ("wait", None)}  # MSCHED queued m1's alternative and bound m2's: m1's would wait on
    with entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", [["m1"], ["m2"]])
        wait_for(lambda: not cell.queued, 5, "the sibling request to be cancelled")
        entity.lot_completed("PASS")
    assert op.machines == ["m2"]
    cancels = [f for cls, f in cell.seen if cls == "CANCEL_RE"]
    assert cancels and cancels[0]["entity_id"] == 7
    assert cell.when("CANCEL_RE")[0] < cell.when("SETUP_RUN")[0]  # cancelled once the winner was taken
    # MSCHED ended m1's request (REQ_CANCEL): nothing of the entity's can be queued, no second CANCEL_RE.
    assert len(cancels) == 1 and cell.seen[-1][0] == "ENTITY_REQ" and cell.seen[-1][1]["action"] == "completed"


def test_a_request_msched_may_still_hold_is_cancelled_before_the_lot_completes(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    cell.comp = {"m1": ("wait", None)}  # queued, never bound
    with entity:
        entity.wait_for_import()
        entity.request_machines("dummy_op", [["m1"]])  # and the script completes without waiting for it
        entity.lot_completed("PASS")
    assert not cell.queued
    told = [(cls, f.get("action")) for cls, f in cell.seen if cls in ("CANCEL_RE", "ENTITY_REQ")]
    assert told[-2:] == [("CANCEL_RE", None), ("ENTITY_REQ", "completed")]


def test_progress_reports_do_not_hold_the_operation_up_and_a_refused_one_fails_the_next_step(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    release = threading.Event()

    async def entity_req(conv: Conversation, m: Message) -> None:
        if m.action != "running":
            return await FakeCell.entity_req(cell, conv, m)
        await asyncio.get_running_loop().run_in_executor(None, release.wait, 10)  # a slow Lot Server
        await conv.send(
            message("Entity_Ack", ack_code=AckCode.NOTNOW, state="failed", note="the operator failed the entity")
        )

    cell.handlers["ENTITY_REQ"] = entity_req
    operated = False
    with pytest.raises(LotError, match="refused running"), entity:
        entity.wait_for_import()
        op = entity.operate("dummy_op", [["m1"]])  # done while the Lot Server sits on the report
        operated = op.ok and not release.is_set()
        release.set()
        entity.lot_completed("PASS")  # waits for the report first: its refusal fails the script here
    assert operated, "the operation waited for the Lot Server's answer to a progress report"
    assert cell.actions()[-2:] == ["running", "failed"]  # and "completed" was never asked


def _shut_unheard(cell: FakeCell, outcome_after: float | None) -> None:
    """The next run's machine goes Shutdown with no death announced (its WC went silent); if
    outcome_after is given, its WC stores the run's outcome that long after (it was frozen, then woke)."""

    async def start(conv: Conversation, m: Message) -> None:
        cell.status(m.machine_id, "Running", m.machine_run_id)
        await conv.send(message("Start_Run_Ack", ack_code=OK))
        if m.machine_run_id != 101:
            return await FakeCell.start(cell, conv, m)
        await cell.broadcast(
            f"wc:{m.machine_id}",
            "UPD_ME_ST",
            message("Update_ME_Status", machine_id=m.machine_id, status="Shutdown", previous="Running"),
        )
        cell.status(m.machine_id, "Shutdown")
        if outcome_after is not None:
            await asyncio.sleep(outcome_after)
            cell.store_pass(m.machine_id, m.machine_run_id)

    cell.handlers["START_RUN"] = start


def test_a_run_whose_machine_went_shutdown_unheard_is_in_doubt_and_counts_once_its_outcome_is_stored(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=5, setup=3, run=60, lost_grace=0.2, in_doubt=20, pause=0.1)
    _shut_unheard(cell, outcome_after=4.0)  # longer than lost_grace: before, the run was counted lost
    op = one_lot(entity, [["m1"], ["m2"]])
    assert op.tries == 1 and op.ok and op.machine_run_id == 101 and op.results == {"RESULT": "PASS"}
    assert [cls for cls, _ in cell.seen].count("START_RUN") == 1, "run once, never twice"


def test_a_setup_that_starts_its_run_unanswered_by_a_machine_gone_shutdown_unheard_leaves_the_run_in_doubt(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    # The SETUP_RUN also starts the run, so a machine lost before its answer may have started it: in doubt,
    # as a START_RUN's, not given up and set up elsewhere. Its frozen WC wakes and stores the run.
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=5, setup=3, run=60, lost_grace=0.2, in_doubt=20, pause=0.1)

    async def start(conv: Conversation, m: Message) -> None:  # the ME told to start, then the WC went silent
        cell.status(m.machine_id, "Shutdown")
        await cell.broadcast(
            f"wc:{m.machine_id}",
            "UPD_ME_ST",
            message("Update_ME_Status", machine_id=m.machine_id, status="Shutdown", previous="Setup"),
        )
        await asyncio.sleep(1.0)
        cell.store_pass(m.machine_id, m.machine_run_id)

    cell.handlers["START_RUN"] = start
    op = one_lot(entity, [["m1"]])
    assert op.tries == 1 and op.ok and op.machine_run_id == 101 and op.results == {"RESULT": "PASS"}
    assert op.runs[0].recipe_id == "dummy_recipe"
    assert [cls for cls, _ in cell.seen].count("SETUP_RUN") == 1, "not set up again: it may have started"


@pytest.mark.parametrize("decision", ["hold", "reroute"])
def test_a_run_in_doubt_past_its_bound_is_the_lot_scripts_decision(
    fake: tuple[FakeCell, OperationEntity], decision: str
) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=5, setup=3, run=60, lost_grace=0.2, in_doubt=1.0, pause=0.1)
    if decision != "hold":
        entity.in_doubt = decision
    _shut_unheard(cell, outcome_after=None)  # never heard of again
    if decision == "hold":

        async def entity_req(conv: Conversation, m: Message) -> None:
            await FakeCell.entity_req(cell, conv, m)
            if m.action == "held":  # the operator sees it held, looks at the part, and fails it (RELEASE_LOT)
                cell.sql("UPDATE lot_status SET state = 'failed' WHERE entity_id = %s", m.entity_id)
                await cell.broadcast(
                    "ls",
                    "LOT_MOVED",
                    message("Lot_Moved", entity_id=m.entity_id, action="fail", lot_id=1),
                    to=f"lot:{m.entity_id}",
                )

        cell.handlers["ENTITY_REQ"] = entity_req
        with pytest.raises(RunInDoubt, match="released as failed by the operator"), entity:
            entity.wait_for_import()
            entity.operate("dummy_op", [["m1"], ["m2"]])
        assert [cls for cls, _ in cell.seen].count("START_RUN") == 1
        assert "held" in cell.actions()
    else:
        with entity:
            entity.wait_for_import()
            op = entity.operate("dummy_op", [["m1"], ["m2"]])
            entity.lot_completed("PASS")
        assert op.tries == 2 and op.ok
    decisions = read_traveller(entity.cfg, 7)["decisions"]  # type: ignore[index]
    released = [(101, "released: fail")] if decision == "hold" else []
    assert [(d["machine_run_id"], d["decision"]) for d in decisions] == [(101, decision), *released]


def test_a_held_entity_whose_run_completes_after_all_counts_the_run(fake: tuple[FakeCell, OperationEntity]) -> None:
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=5, setup=3, run=60, lost_grace=0.2, in_doubt=1.0, pause=0.1)
    _shut_unheard(cell, outcome_after=2.5)  # past the bound (held), then its frozen WC wakes and stores it
    op = one_lot(entity, [["m1"], ["m2"]])
    assert op.tries == 1 and op.ok and op.machine_run_id == 101, op
    assert [cls for cls, _ in cell.seen].count("START_RUN") == 1, "run once, never twice"
    assert cell.actions().count("held") == 1 and "running" in cell.actions()[cell.actions().index("held") :]
    decisions = read_traveller(entity.cfg, 7)["decisions"]  # type: ignore[index]
    assert [d["decision"] for d in decisions] == ["hold", "released: completed"]


def test_a_request_bound_in_a_conversation_given_up_is_found_in_the_tables(
    fake: tuple[FakeCell, OperationEntity],
) -> None:
    # A restarting MSCHED answered the first asks Notnow, so the entity asked again in new conversations;
    # meanwhile it bound the first one's request, answered in the conversation the entity had ended, and
    # refused the new asks: their alt_group was satisfied. The entity finds its binding in the tables.
    cell, entity = fake
    entity.timeouts = Timeouts(answer=3, machines=10, setup=3, run=60, pause=0.1)

    async def mach_req(conv: Conversation, m: Message) -> None:
        cell.sql(
            "INSERT INTO satisfied_alt_groups (entity_id, alt_group, request_key) VALUES (%s, %s, 77) "
            "ON CONFLICT DO NOTHING",
            m.entity_id,
            m.alt_group,
        )
        cell.sql(
            "INSERT INTO reserved_machines (machine_id, entity_id, machine_run_id, request_key) "
            "VALUES ('m1', %s, 101, 77) ON CONFLICT DO NOTHING",
            m.entity_id,
        )
        await conv.send(message("Machine_Req_Ack", ack_code=AckCode.REQ_CANCEL, note="its group is satisfied"))

    cell.handlers["MACH_REQ"] = mach_req
    with entity:
        entity.wait_for_import()
        res = entity.reserve("dummy_op", [["m1"], ["m2"]])
        entity.fail("test over")
    assert (res.machine_run_id, res.request_key, res.machines) == (101, 77, ["m1"])
