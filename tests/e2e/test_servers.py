"""The cell servers as real processes on a real bus and database (issue 6): every conversation
MS, CAS, ERS, LS and SLS answer, with their refusals. The clients (a WC, a lot script, MSCHED, the
operator) are played from the test's own bus attachments, named as the real ones are."""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from gwc.ipc import BlockingBus, BlockingConversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.transport import open_socket
from gwc.log import log_file_name
from gwc.servers.recipe import version_path
from tests.harness import CellHarness, wait_for

OK = AckCode.ACK_OK
MACHINES = [
    {"id": "wc1", "kind": "dummy", "run_time": 0.1, "maintenance_every": 2},
    {"id": "wc2", "kind": "dummy", "run_time": 0.1},
]


def ask(bus: BlockingBus, cls: str, msg: Message, to: str, timeout: float = 10.0) -> Message:
    conv, batch = bus.request(cls, msg, to=to, timeout=timeout)
    conv.end()
    return batch.first


class Ear:
    """A bus attachment of its own (any name, e.g. wc:wc1 or msched) hearing some classes."""

    def __init__(self, cell: CellHarness, name: str, *classes: str) -> None:
        self.bus = BlockingBus(name, cell.cfg.bus, cell.log, classes)
        self.heard: list[tuple[str, Message]] = []

    def drain(self) -> list[tuple[str, Message]]:
        while (conv := self.bus.first_message(timeout=0.01)) is not None:
            assert conv.first is not None
            self.heard.append((conv.cls, conv.first.first))
            conv.end()
        return self.heard

    def wait(self, what: str, pred: Callable[[str, Message], bool], timeout: float = 10.0) -> Message:
        return wait_for(lambda: next((m for c, m in self.drain() if pred(c, m)), None), timeout, what)


@pytest.fixture
def ears() -> Iterator[Callable[..., Ear]]:
    """ears(cell, name, *classes): an Ear, closed after the test."""
    made: list[Ear] = []

    def make(cell: CellHarness, name: str, *classes: str) -> Ear:
        made.append(Ear(cell, name, *classes))
        return made[-1]

    yield make
    for e in made:
        e.bus.close()


@pytest.fixture
def servers(make_cell: Any) -> Callable[..., CellHarness]:
    """servers(*names): a private cell running just these servers (fewer processes, faster tests)."""

    def make(*names: str) -> CellHarness:
        cell = make_cell(machines=MACHINES)
        cell.start_servers(*names)
        return cell

    return make


def q1(cell: CellHarness, sql: str, *params: Any) -> Any:
    rows = cell.query(sql, *params)
    return rows[0] if rows else None


def status_line(cell: CellHarness) -> Message:
    return ask(cell.bus, "STATUS_LN", message("Status_Line_Get"), "sls")


# --------------------------------------------------------------------------------- Machine Server


def change(bus: BlockingBus, machine: str, status: str, expect: list[str] | None = None, **f: Any) -> Message:
    return ask(bus, "CHG_STATUS", message("Change_Status", machine_id=machine, status=status, expect=expect, **f), "ms")


def test_machine_server_changes_status_checked_broadcast_and_refused(servers: Any, ears: Any) -> None:
    cell = servers("ms")
    ear = ears(cell, f"ear.{cell.tag}", "UPD_ME_ST")
    wc = ears(cell, "wc:wc1")
    assert change(wc.bus, "wc1", "Idle", ["Shutdown"]).ack_code == OK
    up = ear.wait("Update_ME_Status Idle", lambda c, m: m.machine_id == "wc1" and m.status == "Idle")
    assert up.previous == "Shutdown"
    # refusals: expect mismatch (with the status now), a transition 6.3.2 has not, bad status, unknown machine
    notnow = change(wc.bus, "wc1", "Setup", ["Shutdown"])
    assert (notnow.ack_code, notnow.status) == (AckCode.NOTNOW, "Idle")
    assert change(wc.bus, "wc1", "Running").ack_code == AckCode.NOTNOW
    assert change(wc.bus, "wc1", "Flying").ack_code == AckCode.BAD_MESSAGE
    assert change(wc.bus, "wc1", "Idle", ["Sleeping"]).ack_code == AckCode.BAD_MESSAGE
    assert change(wc.bus, "nosuch", "Idle").ack_code == AckCode.UNKNOWN
    # a run: recipe, run id, start and end times
    assert change(wc.bus, "wc1", "Setup", ["Idle"], recipe_id="dummy_recipe", machine_run_id=77).ack_code == OK
    assert change(wc.bus, "wc1", "Running", ["Setup"]).ack_code == OK
    st = ask(cell.bus, "GET_STATUS", message("Get_Status", machine_id="wc1"), "ms")
    assert (st.ack_code, st.status, st.recipe_id, st.machine_run_id) == (OK, "Running", "dummy_recipe", 77)
    assert change(wc.bus, "wc1", "Idle", note="run done").ack_code == OK
    start, end, note = q1(cell, "select start_time, end_time, note from machine_status where machine_id = 'wc1'")
    assert start is not None and end is not None and end >= start and note == "run done"
    assert ask(cell.bus, "GET_STATUS", message("Get_Status", machine_id="nosuch"), "ms").ack_code == AckCode.UNKNOWN
    # every change was broadcast, in order
    ear.wait("the Idle after the run", lambda c, m: m.status == "Idle" and m.previous == "Running")
    assert [m.status for c, m in ear.heard if m.machine_id == "wc1"] == ["Idle", "Setup", "Running", "Idle"]


def test_machine_server_lets_one_of_two_racing_changes_win(servers: Any, ears: Any) -> None:
    cell = servers("ms")
    wc = ears(cell, "wc:wc2")
    assert change(wc.bus, "wc2", "Idle", ["Shutdown"]).ack_code == OK
    other = ears(cell, f"other.{cell.tag}")
    convs: list[BlockingConversation] = [
        b.start(
            "CHG_STATUS",
            message("Change_Status", machine_id="wc2", status="Setup", expect=["Idle"], machine_run_id=n),
            to="ms",
        )
        for n, b in ((1, wc.bus), (2, other.bus))
    ]
    answers = [c.next_message(10).first for c in convs]
    for c in convs:
        c.end()
    assert sorted(a.ack_code for a in answers) == sorted([OK, AckCode.NOTNOW])
    winner = 1 if answers[0].ack_code == OK else 2
    assert q1(cell, "select status, machine_run_id from machine_status where machine_id = 'wc2'") == ("Setup", winner)


def test_machine_server_counts_runs_and_the_lots_scrap_and_says_when_maintenance_is_due(
    servers: Any, ears: Any
) -> None:
    cell = servers("ms", "cas")
    wc = ears(cell, "wc:wc1")
    for n, code in ((1, OK), (2, AckCode.RUN_FAIL)):
        conv = wc.bus.start("RUN_COMPL", message("Run_Complete", machine_id="wc1", machine_run_id=n, ack_code=code))
        conv.end()
    wait_for(
        lambda: (
            q1(
                cell,
                "select runs_since_maintenance, scrap_count, maintenance_every from machine_status "
                "where machine_id = 'wc1'",
            )
            == (2, 0, 2)
        ),
        10,
        "2 runs counted (a failed run is no scrap: the lot's verdict says what is)",
    )
    with cell.db() as conn:  # run 2's outcome, as its WC stores it
        conn.execute("insert into machine_run_outcome (machine_run_id, machine_id, ack_code) values (2, 'wc1', 'OK')")
    report = message("Scrap_Report", entity_id=9, machine_id="wc1", machine_run_id=2, parts=2, reason="test")
    assert ask(cell.bus, "SCRAP_RPT", report, "ms").ack_code == OK
    assert ask(cell.bus, "SCRAP_RPT", report, "ms").note == "already reported"  # counted once
    unknown = message("Scrap_Report", entity_id=9, machine_id="wc1", machine_run_id=77, parts=1)
    assert ask(cell.bus, "SCRAP_RPT", unknown, "ms").ack_code == AckCode.UNKNOWN
    assert q1(cell, "select scrap_count from machine_status where machine_id = 'wc1'") == (2,)
    wait_for(
        lambda: q1(cell, "select machine_id from alarms where alarm_id = 'MAINT_DUE' and cleared_at is null"),
        10,
        "alarm MAINT_DUE pending",
    )
    done = ask(cell.bus, "MAINT_DONE", message("Maint_Done", machine_id="wc1", by="test"), "ms")
    assert (done.ack_code, done.runs) == (OK, 2)
    assert q1(cell, "select runs_since_maintenance from machine_status where machine_id = 'wc1'") == (0,)
    assert ask(cell.bus, "MAINT_DONE", message("Maint_Done", machine_id="nosuch"), "ms").ack_code == AckCode.UNKNOWN


def test_silent_wc_makes_its_machine_shutdown_with_alarm_and_broadcast(servers: Any, ears: Any) -> None:
    cell = servers("ms", "cas")
    ear = ears(cell, f"ear.{cell.tag}", "UPD_ME_ST")
    wc = ears(cell, "wc:wc1")
    assert change(wc.bus, "wc1", "Idle", ["Shutdown"]).ack_code == OK
    assert change(wc.bus, "wc1", "Setup", ["Idle"], machine_run_id=5).ack_code == OK
    wc.bus.close()  # as far as the bus can tell, a WC that says nothing more has died
    gone = ear.wait("Update_ME_Status Shutdown", lambda c, m: m.status == "Shutdown", timeout=10)
    assert gone.previous == "Setup" and "silent" in gone.note
    assert q1(cell, "select status from machine_status where machine_id = 'wc1'") == ("Shutdown",)
    wait_for(
        lambda: q1(cell, "select machine_id from alarms where alarm_id = 'WC_SILENT' and cleared_at is null"),
        10,
        "alarm WC_SILENT pending",
    )
    assert q1(cell, "select status from machine_status where machine_id = 'wc2'") == ("Shutdown",)  # was never up


# --------------------------------------------------------------------------------- Cell Alarm Server


def test_alarm_server_records_known_and_unknown_alarms_and_broadcasts_their_clearing(servers: Any, ears: Any) -> None:
    cell = servers("cas", "sls")
    ear = ears(cell, f"ear.{cell.tag}", "ALARM_CLE")
    send = lambda alarm_id, **f: ask(
        cell.bus,
        "ALARM_SEND",
        message("Alarm_Send", alarm_id=alarm_id, raised_by="wc:wc1", machine_id="wc1", **f),
        "cas",
    )
    known = send("HOME_CMM")
    assert (known.ack_code, known.known) == (OK, True)
    unknown = send("SPILT_COFFEE", alarm_text="coffee on the CMM")
    assert (unknown.ack_code, unknown.known) == (OK, False)
    assert send(" ").ack_code == AckCode.BAD_MESSAGE
    rows = cell.query("select alarm_no, alarm_id, known, alarm_text, raised_by from alarms order by alarm_no")
    assert rows == [
        (known.alarm_no, "HOME_CMM", True, "Push the start button on the CMM", "wc:wc1"),
        (unknown.alarm_no, "SPILT_COFFEE", False, "coffee on the CMM", "wc:wc1"),
    ]
    line = status_line(cell)
    assert line.alarms == 2 and f"#{unknown.alarm_no} (unknown): coffee on the CMM" in line.text
    clear = lambda no, by="op": ask(
        cell.bus,
        "ALARM_CLR_REQ",
        message("Alarm_Clear_Request", alarm_no=no, cleared_by=by),
        "cas",
    )
    assert clear(known.alarm_no).ack_code == OK
    heard = ear.wait("ALARM_CLEAR broadcast", lambda c, m: m.alarm_no == known.alarm_no)
    assert (heard.alarm_id, heard.machine_id, heard.cleared_by) == ("HOME_CMM", "wc1", "op")
    again = clear(known.alarm_no)
    assert again.ack_code == AckCode.NOTNOW and "already cleared by op" in again.note
    assert clear(9999).ack_code == AckCode.UNKNOWN
    assert clear(unknown.alarm_no, by=" ").ack_code == AckCode.BAD_MESSAGE
    assert q1(cell, "select cleared_by from alarms where alarm_no = %s", known.alarm_no) == ("op",)
    assert status_line(cell).alarms == 1


# --------------------------------------------------------------------------------- Equipment Recipe Server


def fetch(cell: CellHarness, recipe: str, machine: str | None = None) -> Message:
    return ask(cell.bus, "RECIPE_GET", message("Recipe_Fetch", recipe_id=recipe, machine_id=machine), "ers")


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def test_recipe_server_versions_approves_and_serves_only_the_approved_file(servers: Any) -> None:
    cell = servers("ers")
    got = fetch(cell, "dummy_recipe", "wc1")
    assert (got.ack_code, got.version) == (OK, 1) and sha(got.content) == got.checksum
    assert fetch(cell, "nosuch", "wc1").ack_code == AckCode.REC_INVAL
    assert fetch(cell, "alum_chess_set", "wc1").ack_code == AckCode.REC_INVAL  # not for this machine
    store = lambda rid, text: ask(
        cell.bus,
        "RECIPE_PUT",
        message("Recipe_Store", recipe_id=rid, content=text, by="test"),
        "ers",
    )
    v1 = store("probe", "PROBE 1\n")
    assert (v1.ack_code, v1.version, v1.checksum) == (OK, 1, sha("PROBE 1\n"))
    assert store("probe", "PROBE 1\n").version == 1  # the same content is no new version
    assert store("../etc/passwd", "x").ack_code == AckCode.BAD_MESSAGE
    assert store("big", "x" * 50_000).ack_code == AckCode.BAD_MESSAGE
    assert fetch(cell, "probe").ack_code == AckCode.REC_INVAL  # nothing approved yet
    approve = lambda rid, v=None: ask(
        cell.bus,
        "RECIPE_APPR",
        message("Recipe_Approve", recipe_id=rid, version=v, by="test"),
        "ers",
    )
    assert approve("probe").version == 1
    assert fetch(cell, "probe").content == "PROBE 1\n"
    assert approve("probe", 7).ack_code == AckCode.UNKNOWN
    assert approve("nosuch").ack_code == AckCode.UNKNOWN
    # the file on disk edited after approval: served as it is, with the approved checksum -> the WC refuses it
    path = version_path(cell.cfg, "probe", 1)
    path.write_text("PROBE 1\nRAPID 9999\n")
    tampered = fetch(cell, "probe")
    assert tampered.ack_code == OK and sha(tampered.content) != tampered.checksum
    # approving again takes the edit as a new version and puts the original back
    again = approve("probe")
    assert (again.ack_code, again.version) == (OK, 2) and "edited" in again.note
    assert path.read_text() == "PROBE 1\n"
    good = fetch(cell, "probe")
    assert (good.version, good.content) == (2, "PROBE 1\nRAPID 9999\n") and sha(good.content) == good.checksum
    assert cell.query("select version, approved from recipe_versions where recipe_id = 'probe' order by 1") == [
        (1, False),
        (2, True),
    ]
    assert q1(cell, "select content from recipe_versions where recipe_id = 'probe' and version = 1")[0] == b"PROBE 1\n"


# --------------------------------------------------------------------------------- Lot Server


def entity(bus: BlockingBus, eid: int, action: str, **f: Any) -> Message:
    return ask(bus, "ENTITY_REQ", message("Entity_Request", entity_id=eid, action=action, **f), "ls")


def decide(bus: BlockingBus, eid: int, action: str, cls: str | None = None) -> Message:
    cls = cls or ("IMPORT_LOT" if action == "import" else "EXPORT_LOT")
    return ask(bus, cls, message("Lot_Decision", entity_id=eid, action=action, by="op"), "ls")


def state_of(cell: CellHarness, eid: int) -> str:
    return q1(cell, "select state from lot_status where entity_id = %s", eid)[0]


def test_lot_server_moves_entities_through_their_life_with_the_operators_decisions(servers: Any, ears: Any) -> None:
    cell = servers("ls", "sls")
    ear = ears(cell, f"ear.{cell.tag}", "LOT_MOVED")
    bus = cell.bus
    create = lambda **f: ask(bus, "CREATE_LOT", message("Create_Lot_Entity", **f), "ls")
    made = create(product_id="alum_chess_set", quantity=2, priority=5, owner="op", result_params=["p1", "p2"])
    assert made.ack_code == OK and len(made.entity_ids) == 2
    e1, e2 = made.entity_ids
    # Two lot scripts on the bus, as waiting for import: they listen to no broadcast (gwc/lot/model.py)
    script, other = ears(cell, f"lot:{e1}"), ears(cell, f"lot:{e2}")
    assert q1(
        cell, "select quantity, priority, script_id, lot_type, result_params from lots where lot_id = %s", made.lot_id
    ) == (2, 5, "chess", "CMM_LOT", ["p1", "p2"])
    more = create(product_id="alum_chess_set", quantity=1, lot_id=made.lot_id)
    assert more.lot_id == made.lot_id and q1(
        cell, "select unit from lot_entities where entity_id = %s", more.entity_ids[0]
    ) == (3,)
    # asked again (its answer was lost, or the Lot Server restarted): what the first request made
    once = create(product_id="milled_pawn", quantity=2, request_id="op.1")
    again = create(product_id="milled_pawn", quantity=2, request_id="op.1")
    assert (again.ack_code, again.lot_id, again.entity_ids, again.note) == (
        OK,
        once.lot_id,
        once.entity_ids,
        "already created",
    )
    assert q1(cell, "select count(*) from lot_entities where create_request = 'op.1'") == (2,)
    assert create(product_id="nosuch", quantity=1).ack_code == AckCode.UNKNOWN
    assert create(product_id="alum_chess_set", quantity=0).ack_code == AckCode.BAD_MESSAGE
    assert create(product_id="alum_chess_set", quantity=1, lot_id=99999).ack_code == AckCode.UNKNOWN
    assert state_of(cell, e1) == "created"
    # refusals of ENTITY_REQ
    assert entity(bus, e1, "fly").ack_code == AckCode.BAD_MESSAGE
    assert entity(bus, 99999, "import").ack_code == AckCode.UNKNOWN
    assert entity(bus, e1, "export").ack_code == AckCode.NOTNOW
    assert entity(bus, e1, "failed").ack_code == AckCode.BAD_MESSAGE  # no reason
    assert entity(bus, e1, "attach").ack_code == AckCode.BAD_MESSAGE  # no pid
    # import: the entity asks, the status line shows it, the operator decides, the entity is told
    asked = entity(bus, e1, "import")
    assert (asked.ack_code, asked.state, asked.lot_id) == (OK, "waiting_import", made.lot_id)
    line = status_line(cell)
    assert line.imports == 1 and f"IMPORT 1 waiting ({e1})" in line.text
    assert decide(bus, e1, "export").ack_code == AckCode.NOTNOW
    assert decide(bus, e1, "export", cls="IMPORT_LOT").ack_code == AckCode.BAD_MESSAGE
    assert decide(bus, 99999, "import").ack_code == AckCode.UNKNOWN
    assert decide(bus, e1, "import").ack_code == OK
    assert ear.wait("LOT_MOVED import", lambda c, m: m.entity_id == e1).action == "import"
    # ... and the entity's own script is told, addressed to it; the other lot's script hears nothing
    assert script.wait("LOT_MOVED to lot:e1", lambda c, m: c == "LOT_MOVED" and m.entity_id == e1).action == "import"
    assert other.drain() == []
    assert decide(bus, e1, "import").ack_code == AckCode.NOTNOW  # not waiting any more
    for action in ("waiting_machine", "running", "completed"):
        assert entity(bus, e1, action).state == action
    assert entity(bus, e1, "destroy").ack_code == AckCode.NOTNOW  # in the cell
    assert entity(bus, e1, "export").state == "waiting_export"
    assert status_line(cell).exports == 1
    assert decide(bus, e1, "export").ack_code == OK
    assert state_of(cell, e1) == "exported"
    # exported and imported again: a new lot (6.1.1)
    back = entity(bus, e1, "import")
    assert back.ack_code == OK and back.lot_id != made.lot_id
    assert decide(bus, e1, "import").lot_id == back.lot_id
    assert q1(cell, "select lot_id from lot_entities where entity_id = %s", e1) == (back.lot_id,)
    assert q1(cell, "select product_id, quantity from lots where lot_id = %s", back.lot_id) == ("alum_chess_set", 1)
    # failure and destruction
    assert entity(bus, e2, "failed", reason="dropped on the floor").state == "failed"
    assert q1(cell, "select reason from lot_status where entity_id = %s", e2) == ("dropped on the floor",)
    assert entity(bus, e2, "destroy").ack_code == OK
    assert entity(bus, e2, "import").ack_code == AckCode.UNKNOWN
    assert entity(bus, e2, "state").note == "destroyed"


def test_lot_server_divides_and_merges_entities_before_work_starts(servers: Any) -> None:
    cell = servers("ls")
    bus = cell.bus
    made = ask(bus, "CREATE_LOT", message("Create_Lot_Entity", product_id="milled_pawn", quantity=1), "ls")
    (e,) = made.entity_ids
    dm = lambda **f: ask(bus, "DIV_MERGE", message("Divide_Merge", **f), "ls")
    split = dm(entity_id=e, action="divide", quantity=2)
    assert split.ack_code == OK and split.entity_ids[0] == e and len(split.entity_ids) == 3
    child = split.entity_ids[1]
    assert q1(cell, "select parent_entity_id, lot_id from lot_entities where entity_id = %s", child) == (e, made.lot_id)
    merged = dm(entity_id=e, action="merge", other_entity_id=child)
    assert (merged.ack_code, merged.entity_ids) == (OK, [e])
    assert entity(bus, child, "state").note == "destroyed"
    assert dm(entity_id=e, action="merge", other_entity_id=child).ack_code == AckCode.UNKNOWN
    assert dm(entity_id=e, action="merge").ack_code == AckCode.BAD_MESSAGE
    assert dm(entity_id=e, action="shred").ack_code == AckCode.BAD_MESSAGE
    assert dm(entity_id=99999, action="divide").ack_code == AckCode.UNKNOWN
    entity(bus, e, "import")
    assert dm(entity_id=e, action="divide").ack_code == AckCode.NOTNOW  # waiting_import: not now


def test_dead_lot_script_fails_its_entity_and_msched_is_asked_to_free_its_machines(servers: Any, ears: Any) -> None:
    cell = servers("ls")
    made = ask(cell.bus, "CREATE_LOT", message("Create_Lot_Entity", product_id="alum_chess_set", quantity=2), "ls")
    e, finished = made.entity_ids
    msched = ears(cell, "msched", "CANCEL_RE", "UNRESERVE")
    script = ears(cell, f"lot:{e}")
    attached = entity(script.bus, e, "attach", script_pid=os.getpid())
    assert attached.ack_code == OK and attached.state == "created"
    # All a lot script needs to start: its lot and its lot script (here its product's: the chess script).
    assert (attached.product_id, attached.script_id, attached.script_path) == (
        "alum_chess_set",
        "chess",
        "gwc/lot/scripts/chess.py",
    )
    assert entity(script.bus, e, "import").ack_code == OK
    done = ears(cell, f"lot:{finished}")  # a script whose entity is finished may go quietly
    entity(done.bus, finished, "attach", script_pid=os.getpid())
    entity(done.bus, finished, "failed", reason="test")
    done.bus.close()
    script.bus.close()  # the script is gone
    asked: dict[str, Message] = {}

    def answer_msched() -> bool:
        while (conv := msched.bus.first_message(timeout=0.05)) is not None:
            req = conv.first.first
            asked[conv.cls] = req
            ack = "Cancel_Req_Ack" if conv.cls == "CANCEL_RE" else "Unreserve_Me_Ack"
            conv.send(message(ack, ack_code=OK))
            conv.end()
        return len(asked) == 2

    wait_for(answer_msched, 10, "LS to ask msched CANCEL_RE and UNRESERVE")
    assert asked["CANCEL_RE"].entity_id == e and asked["UNRESERVE"].entity_id == e
    assert asked["UNRESERVE"].machine_id is None  # all of its machines
    assert q1(cell, "select state, reason from lot_status where entity_id = %s", e)[0] == "failed"
    assert "lot script died" in q1(cell, "select reason from lot_status where entity_id = %s", e)[0]
    assert q1(cell, "select reason from lot_status where entity_id = %s", finished) == ("test",)


# --------------------------------------------------------------------------------- the operator's commands


def gwc(cell: CellHarness, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=cell.env(), capture_output=True, text=True, timeout=60
    )


def test_operator_commands_list_and_clear_alarms_show_the_status_line_and_keep_the_recipe_library(
    servers: Any, tmp_path: Any
) -> None:
    cell = servers("cas", "sls", "ers")
    no = ask(cell.bus, "ALARM_SEND", message("Alarm_Send", alarm_id="HOME_CMM", raised_by="wc:cmm_wc"), "cas").alarm_no
    listed = gwc(cell, "alarm", "list")
    assert listed.returncode == 0 and "Push the start button" in listed.stdout, listed.stderr
    line = gwc(cell, "status-line")
    assert line.returncode == 0 and f"ALARMS 1 pending, newest #{no}" in line.stdout, line.stderr
    assert gwc(cell, "alarm", "clear", str(no)).returncode == 0
    again = gwc(cell, "alarm", "clear", str(no))
    assert again.returncode == 1 and again.stderr.startswith("gwc: refused with Notnow")
    assert str(no) in gwc(cell, "alarm", "list", "--all").stdout
    assert gwc(cell, "alarm", "list").stdout.strip() == "(none)"
    recipe = tmp_path / "probe.txt"
    recipe.write_text("PROBE 2\n")
    added = gwc(cell, "recipe", "add", "probe", str(recipe), "--description", "a probe", "--approve")
    assert added.returncode == 0 and "probe v1 approved" in added.stdout, added.stderr
    version_path(cell.cfg, "probe", 1).write_text("PROBE 3\n")
    listing = gwc(cell, "recipe", "list")
    assert "MODIFIED" in next(ln for ln in listing.stdout.splitlines() if ln.startswith("probe")), listing.stdout
    approved = gwc(cell, "recipe", "approve", "probe")
    assert approved.returncode == 0 and "probe v2 approved" in approved.stdout, approved.stderr
    shown = gwc(cell, "recipe", "show", "probe")
    assert shown.returncode == 0 and shown.stdout.endswith("--- probe v2 ---\nPROBE 3\n"), shown.stdout
    missing = gwc(cell, "recipe", "approve", "nosuch")
    assert missing.returncode == 1 and "Unknown" in missing.stderr


# --------------------------------------------------------------------------------- database failure (3.2.2)


def test_servers_answer_db_badrea_while_the_database_is_gone_and_serve_again_when_it_is_back(
    make_cell: Any, pg_cluster: Any, database_url: str
) -> None:
    cell = make_cell(machines=MACHINES)
    cell.start_servers("cas", "ms", "sls")
    pids = {n: cell.pid(n) for n in ("cas", "ms", "sls")}
    assert ask(cell.bus, "GET_STATUS", message("Get_Status", machine_id="wc1"), "ms").ack_code == OK
    dbname = database_url.split("@/", 1)[1].split("?", 1)[0]
    with pg_cluster.admin() as conn:
        conn.execute(f'drop database "{dbname}" with (force)')
    status = ask(cell.bus, "GET_STATUS", message("Get_Status", machine_id="wc1"), "ms")
    assert (status.name, status.ack_code) == ("Status_Reply", AckCode.DB_BADREA)
    alarm = ask(cell.bus, "ALARM_SEND", message("Alarm_Send", alarm_id="HOME_CMM", raised_by="t"), "cas")
    assert alarm.ack_code == AckCode.DB_BADREA
    line = ask(cell.bus, "STATUS_LN", message("Status_Line_Get"), "sls")
    assert line.text.startswith("DATABASE DOWN for"), line.text
    for name in ("ms", "cas", "sls"):
        wait_for(lambda n=name: cell.log_has(n, "the cell database is away"), 10, f"{name} to notice")
    # Back (a database of the same name at the same address): served again, by the same processes.
    with pg_cluster.admin() as conn:
        conn.execute(f'create database "{dbname}" template {pg_cluster.template}')
    wait_for(
        lambda: ask(cell.bus, "GET_STATUS", message("Get_Status", machine_id="wc1"), "ms").ack_code == OK,
        15,
        "the Machine Server to serve again",
    )
    wait_for(
        lambda: (
            ask(cell.bus, "ALARM_SEND", message("Alarm_Send", alarm_id="HOME_CMM", raised_by="t"), "cas").ack_code == OK
        ),
        15,
        "the Cell Alarm Server to serve again",
    )
    wait_for(
        lambda: "ALARMS 1 pending" in ask(cell.bus, "STATUS_LN", message("Status_Line_Get"), "sls").text,
        15,
        "the status line to show the alarm",
    )
    assert {n: cell.pid(n) for n in pids} == pids and all(cell.alive(n) for n in pids)


# --------------------------------------------------------------------------------- the bus's heartbeat


def test_the_servers_of_a_host_beat_together_at_the_ticks_of_its_clock(servers: Any) -> None:
    """Heartbeats fall on the ticks of the host's clock (docs/protocol.md, Membership): the beats of
    the servers, each a process started at its own moment, arrive together, just after each tick."""
    cell = servers("ms", "cas", "ers", "sls")
    hb = cell.cfg.bus.heartbeat
    sock = open_socket(cell.cfg.bus, cell.cfg.bus.port + 1)  # the beat port
    sock.settimeout(0.1)
    phases: list[float] = []
    try:
        deadline = time.monotonic() + 10
        while len(phases) < 40 and time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError):
                sock.recv(65536)
                phases.append(time.monotonic() % hb)
    finally:
        sock.close()
    assert len(phases) >= 40, f"{len(phases)} beats heard in 10 s"
    from_tick = sorted(min(p, hb - p) for p in phases)  # scattered beats: uniform over [0, hb/2]
    assert from_tick[len(from_tick) // 2] < hb / 8, from_tick


def test_the_servers_no_lot_talks_to_never_hear_a_lot_script_come_and_go(make_cell: Any, ears: Any) -> None:
    """The CAS, ERS and SLS ignore lot scripts (docs/protocol.md, *Peers a module ignores*): a lot's
    sign-on and bye reach the Lot Server, which watches lot scripts, and are dropped before they wake
    the others, which still answer everyone else."""
    cell = make_cell(machines=MACHINES, level="trace")  # a lot's coming and going is logged at trace
    cell.start_servers("ls", "cas", "ers", "sls")
    logs = {name: cell.cfg.log_dir / log_file_name(name) for name in ("ls", "cas", "ers", "sls")}
    lot = ears(cell, "lot:4242", "RUN_COMPL", "UPD_ME_ST")
    wait_for(lambda: "lot:4242 joined the bus" in logs["ls"].read_text(), 10, "the Lot Server to take the lot")
    lot.bus.close()
    wait_for(lambda: "lot:4242 left the bus" in logs["ls"].read_text(), 10, "the Lot Server to hear its bye")
    # Each answers a question asked after the bye: it has read (or the kernel dropped) what came before.
    assert status_line(cell).text
    cleared = ask(cell.bus, "ALARM_CLR_REQ", message("Alarm_Clear_Request", alarm_no=999999, cleared_by="t"), "cas")
    assert cleared.ack_code != OK
    fetched = ask(cell.bus, "RECIPE_GET", message("Recipe_Fetch", recipe_id="no_such_recipe"), "ers")
    assert fetched.ack_code != OK
    for name in ("cas", "ers", "sls"):
        text = logs[name].read_text()
        assert "joined the bus" in text, f"{name} logs its peers at trace"
        assert "lot:4242" not in text, f"{name} heard the lot script"
