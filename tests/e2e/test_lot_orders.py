"""Lots end to end, everything real: work order -> lot scripts -> MSCHED -> WC/ME -> results -> export.

Each test runs a private cell (tests/harness.py) with every server, and drives it as the operator
does, through `gwc` commands; the lot scripts are the processes `gwc order new` starts.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from typing import Any

from tests.e2e.lotkit import (
    cell_with_machines,
    gwc,
    holdings,
    import_export_all,
    lot_log,
    ok,
    order,
    script_pid,
    state,
    steps,
    wait_state,
)
from tests.harness import CellHarness, wait_for

CMM = {"id": "cmm_wc", "kind": "cmm", "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0}}


def test_chess_order_goes_from_work_order_to_exported_lots_in_fifo_order(lot_cell: Any) -> None:
    # The CMM's WC logs at trace, where a peer's coming and going is logged (lot scripts' included).
    cmm = {**CMM, "sim": {"measure_time": 0.4, "pattern": "P"}, "level": "trace"}
    cell = cell_with_machines(lot_cell(machines=[cmm]), "cmm_wc")
    entities = order(cell, "alum_chess_set=3")
    assert len(entities) == 3
    for e in entities:
        wait_state(cell, e, "waiting_import")
    listing = {r["entity"]: r for r in json.loads(ok(gwc(cell, "lots", "--json")))}
    assert {listing[e]["state"] for e in entities} == {"waiting_import"}
    assert all(listing[e]["script"].isdigit() for e in entities), listing  # each script's process is alive

    # Import in reverse entity order, each after the previous has asked for the CMM: FIFO serves the
    # requests in the order they came, whatever the entity ids.
    first, second, third = reversed(entities)
    ok(gwc(cell, "import", str(first)))
    wait_state(cell, first, "running", "completed", "waiting_export")
    ok(gwc(cell, "import", str(second)))
    served = ("running", "completed", "waiting_export")
    wait_for(
        lambda: sum(holdings(cell, second)) or state(cell, second)[0] in served,
        15,
        "the second lot's request to be queued (or served)",
    )
    ok(gwc(cell, "import", str(third)))
    # The first lot's whole operation is done, the others have waited to be imported: none of the three
    # scripts opened a database connection (docs/lot-scripts.md, *The database*). One, once opened, is
    # held until its script ends.
    wait_state(cell, first, "waiting_export")
    assert cell.query("SELECT count(*) FROM pg_stat_activity WHERE application_name = 'gwc_lot'") == [(0,)]
    import_export_all(cell, entities)

    runs = {e: [s["machine_run_id"] for s in steps(cell, e)] for e in entities}
    assert all(len(r) == 1 for r in runs.values()), runs
    assert runs[first][0] < runs[second][0] < runs[third][0], f"not FIFO: {runs}"
    for e in entities:
        st, reason = state(cell, e)
        assert st == "exported" and reason.startswith("PASS"), (e, st, reason)
        assert holdings(cell, e) == (0, 0)
        log = lot_log(cell, e)
        for told in ("attached", "imported", "got machine_run_id", "run", "complete", "unreserved", "exported"):
            assert told in log, f"lot:{e} log does not tell '{told}'"
        # The WC does not track lot scripts, yet named this one as the listener its Run_Complete must
        # reach (docs/protocol.md, *Peers a module ignores*): heard on the bus, not read back from the tables.
        assert f"run {runs[e][0]} complete: cmm_wc" in log and "no RUN_COMPL came" not in log, log
        assert f"lot:{e} joined the bus" not in cell.log_text("wc:cmm_wc")
    assert "ms joined the bus" in cell.log_text("wc:cmm_wc")  # (what it does track, it logs at trace)
    # Each traveller was saved several times, swapped with its previous version (gwc/files.py): the
    # previous versions go as the scripts end, and no save left a file of its own behind.
    travellers = sorted(f"entity-{e}.json" for e in entities)
    lots_dir = cell.cfg.var / "lots"
    wait_for(lambda: sorted(p.name for p in lots_dir.iterdir()) == travellers, 20, "only the travellers in var/lots")
    results = cell.query(
        "SELECT machine_run_id, param, value FROM machine_run_result WHERE machine_id = 'cmm_wc' "
        "AND param = 'RESULT' ORDER BY 1"
    )
    assert [(r[0], r[2]) for r in results] == [(runs[e][0], "PASS") for e in (first, second, third)]
    # every module tells its part
    assert "MACH_REQ" in cell.log_text("msched")
    assert re.search(r"run \d+ complete", cell.log_text("wc:cmm_wc"))
    assert "exported" in cell.log_text("ls") and "lot script attached" in cell.log_text("ls")
    assert "work order" in cell.log_text("hi")
    orders = json.loads(ok(gwc(cell, "order", "list", "--json")))
    assert orders[-1]["status"] == "DONE" and orders[-1]["items"] == "3 x alum_chess_set"
    shown = ok(gwc(cell, "lots", str(first)))
    assert "alum_chess" in shown and "RESULT=PASS" in shown


def _first_on_the_cmm(cell: CellHarness) -> list[int]:
    """Order two chess sets and import the first: once the CMM measures it, return both."""
    entities = order(cell, "alum_chess_set=2")
    for e in entities:
        wait_state(cell, e, "waiting_import")
    ok(gwc(cell, "import", str(entities[0])))
    wait_for(
        lambda: cell.query("SELECT status FROM machine_status WHERE machine_id = 'cmm_wc'")[0][0] == "Running",
        20,
        "the CMM to run the first lot",
    )
    return entities


def test_lot_script_killed_mid_run_leaves_its_machine_free_and_its_entity_failed(lot_cell: Any) -> None:
    cell = cell_with_machines(lot_cell(machines=[{**CMM, "sim": {"measure_time": 2.0, "pattern": "P"}}]), "cmm_wc")
    killed, other = _first_on_the_cmm(cell)
    pid = script_pid(cell, killed)
    assert pid
    os.kill(pid, signal.SIGKILL)
    t0 = time.monotonic()
    wait_for(
        lambda: state(cell, killed)[0] == "failed" and holdings(cell, killed) == (0, 0),
        10,
        "the killed lot's entity failed and its machine unreserved",
    )
    assert time.monotonic() - t0 < 10
    assert "died" in (state(cell, killed)[1] or "")
    import_export_all(cell, [other])  # the CMM serves the next lot as if nothing happened
    assert state(cell, other)[1].startswith("PASS")
    check = gwc(cell, "check", "--no-bus")
    assert check.returncode == 0, check.stdout + check.stderr


def test_request_cancelled_from_the_human_interface_reaches_the_lot_as_req_cancel(lot_cell: Any) -> None:
    # The first lot holds the CMM while the second's request is imported, listed and cancelled: three
    # `gwc` processes, which on a loaded machine took longer than a 4 s measurement (the request was bound).
    cell = cell_with_machines(lot_cell(machines=[{**CMM, "sim": {"measure_time": 12.0, "pattern": "P"}}]), "cmm_wc")
    first, cancelled = _first_on_the_cmm(cell)
    ok(gwc(cell, "import", str(cancelled)))
    wait_for(lambda: holdings(cell, cancelled)[0], 15, "the second lot's request to be queued")
    key = cell.query("SELECT request_key FROM request_machines WHERE entity_id = %s", cancelled)[0][0]
    listed = json.loads(ok(gwc(cell, "requests", "--json")))  # Listing 8's screen lists it ...
    queue = listed[0]["requests"] if isinstance(listed, list) and listed and "requests" in listed[0] else listed
    assert any(r.get("request_key") == key for r in queue), listed
    ok(gwc(cell, "cancel", str(key)))  # ... and its Do It cancels it
    wait_state(cell, cancelled, "failed")
    assert "REQ_CANCEL" in lot_log(cell, cancelled)
    assert "REQ_CANCEL" in (state(cell, cancelled)[1] or "")
    assert holdings(cell, cancelled) == (0, 0)
    assert steps(cell, cancelled) == []
    import_export_all(cell, [first])


def test_bad_arguments_give_one_clear_line(lot_cell: Any) -> None:
    cell = lot_cell(machines=[])
    cell.start_servers("ls")
    cases = (
        (("import", "99999"), "unknown lot entity 99999"),
        (("export", "99999"), "unknown lot entity 99999"),
        (("lots", "99999"), "unknown lot entity 99999"),
        (("order", "show", "4242"), "unknown work order 4242"),
        (("order", "new", "--customer", "NJIT", "no_such_product=1"), "unknown product"),
        (("order", "new", "--customer", "NOBODY", "alum_chess_set=1"), "unknown customer"),
        (("order", "new", "--customer", "NJIT", "alum_chess_set=x"), "bad order item"),
        (("script", "register", "s", "/no/such/file.py"), "does not exist"),
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "gwc", *args],
            env=cell.env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for args, _ in cases
    ]  # at once: it is quicker
    for (args, says), proc in zip(cases, procs):
        out, err = proc.communicate(timeout=60)
        lines = err.strip().splitlines()
        assert proc.returncode != 0, args
        assert len(lines) == 1 and lines[0].startswith("gwc: ") and says in lines[0], (args, err)
        assert "Traceback" not in err + out


def test_an_order_the_lot_server_answers_too_late_is_asked_again_and_its_lot_made_once(lot_cell: Any) -> None:
    # The Lot Server is held up past the HI's deadline (the test holds the counter row its next lot
    # id comes from): the HI asks again with the same request_id, and once let go the Lot Server
    # makes the lot for the first request and answers the repeat with that same lot.
    cell = lot_cell(machines=[])
    cell.start_servers("ls")
    order(cell, "milled_pawn=1")  # a lot made as usual: the counter row exists
    hold = cell.db()
    proc: subprocess.Popen[str] | None = None
    try:
        with hold.transaction():
            hold.execute("SELECT value FROM max_values WHERE type = 'LOT_ID' FOR UPDATE")
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "gwc",
                    "order",
                    "new",
                    "--customer",
                    "NJIT",
                    "--no-scripts",
                    "milled_pawn=2",
                    "--json",
                ],
                env=cell.env(),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            wait_for(
                lambda: "did not take CREATE_LOT (restarting?): asking again" in cell.log_text("hi"),
                30,
                "the HI to ask again",
            )
        out, err = proc.communicate(timeout=30)
    finally:
        hold.close()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    (lot,) = json.loads(out)["lots"]
    assert len(lot["entities"]) == 2
    wo = json.loads(out)["work_order_id"]
    assert cell.query("SELECT lot_id FROM lots WHERE work_order_id = %s", wo) == [(lot["lot_id"],)]
    assert cell.query("SELECT count(*) FROM lot_entities WHERE lot_id = %s", lot["lot_id"]) == [(2,)]
    assert re.search(
        rf"CREATE_LOT \S+ asked again: lot {lot['lot_id']}, entities .*already created", cell.log_text("ls")
    )
