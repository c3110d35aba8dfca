"""A lot script a user writes and registers, run for real; its mill dies mid-run, or after the run but
before announcing it, and it carries on."""

from __future__ import annotations

import json
import os
import re
import signal
from pathlib import Path
from typing import Any

from tests.e2e.lotkit import (
    cell_with_machines,
    gwc,
    import_export_all,
    lot_log,
    ok,
    order,
    start_machine,
    state,
    steps,
    wait_state,
)
from tests.harness import wait_for

SCRIPT = '''"""Mill a bare pawn: no measuring."""

import dataclasses

from gwc.lot import OperationEntity

IN_DOUBT = None  # or (decision, seconds): what to do with a run in doubt, and after how long


def main(entity: OperationEntity) -> None:
    if IN_DOUBT:
        entity.in_doubt = IN_DOUBT[0]
        entity.timeouts = dataclasses.replace(entity.timeouts, in_doubt=IN_DOUBT[1])
    entity.wait_for_import()
    op = entity.operate("mill_chess")
    entity.lot_completed(f"PASS: milled on {op.machines[0]} (try {op.tries})")
    entity.wait_for_export()
'''


def milling_on_the_mazak(
    lot_cell: Any, tmp_path: Path, run_time: float, in_doubt: tuple[str, float] | None = None
) -> tuple[Any, int]:
    """The registered script's pawn imported and milling on the Mazak; wc2, the other mill, up too."""
    cell = cell_with_machines(
        lot_cell(
            machines=[
                {"id": "mazak", "kind": "dummy", "run_time": run_time, "liveness": 1.0},
                {"id": "wc2", "kind": "dummy", "run_time": 0.3},
            ]
        ),
        "mazak",
    )
    script = tmp_path / "bare_pawn.py"
    script.write_text(SCRIPT.replace("IN_DOUBT = None", f"IN_DOUBT = {in_doubt!r}"))
    ok(gwc(cell, "script", "register", "bare_pawn", str(script), "--product", "bare_pawn"))
    (pawn,) = order(cell, "bare_pawn=1")
    wait_state(cell, pawn, "waiting_import")
    ok(gwc(cell, "import", str(pawn)))
    wait_for(
        lambda: cell.query("SELECT status FROM machine_status WHERE machine_id = 'mazak'")[0][0] == "Running",
        20,
        "the Mazak to mill",
    )
    start_machine(cell, "wc2")  # started after the Mazak took the pawn: where a second milling goes
    return cell, pawn


def mazak_run(cell: Any) -> int:
    return int(cell.query("SELECT machine_run_id FROM machine_status WHERE machine_id = 'mazak'")[0][0])


def outcome(cell: Any, machine: str, run: int) -> list[tuple[Any, ...]]:
    return cell.query(
        "SELECT ack_code FROM machine_run_outcome WHERE machine_id = %s AND machine_run_id = %s", machine, run
    )


def test_a_wc_frozen_past_its_liveness_mid_run_the_run_completes_once_and_counts(lot_cell: Any, tmp_path: Path) -> None:
    cell, pawn = milling_on_the_mazak(lot_cell, tmp_path, run_time=6.0)
    run = mazak_run(cell)
    wc = cell.pid("wc", "mazak")
    os.kill(wc, signal.SIGSTOP)  # frozen: silent, not dead; its ME goes on milling
    try:
        wait_for(
            lambda: cell.query("SELECT status FROM machine_status WHERE machine_id = 'mazak'")[0][0] == "Shutdown",
            10,
            "the Machine Server to shut the silent Mazak down (liveness 1 s)",
        )
        results = cell.cfg.results_dir / "mazak" / f"run-{run}.txt"
        wait_for(results.exists, 20, "the ME to finish the run while its WC is frozen")
    finally:
        os.kill(wc, signal.SIGCONT)
    import_export_all(cell, [pawn], timeout=60)

    st, reason = state(cell, pawn)
    assert st == "exported" and reason == "PASS: milled on mazak (try 1)", reason
    assert [s["machines"] for s in steps(cell, pawn)] == [["mazak"]]
    assert outcome(cell, "mazak", run) == [("ACK_OK",)]
    assert cell.query("SELECT count(*) FROM machine_run_result WHERE machine_id = 'wc2'")[0][0] == 0, "run twice"


def test_a_wc_frozen_past_the_runs_bound_the_scripts_decision_is_taken_logged_and_the_late_run_recorded(
    lot_cell: Any, tmp_path: Path
) -> None:
    # The script's decision is the safe default, hold: the entity is held, the operator sees it in the
    # dispatch list and releases it to reroute.
    cell, pawn = milling_on_the_mazak(lot_cell, tmp_path, run_time=3.0, in_doubt=("hold", 2.0))
    run = mazak_run(cell)
    wc = cell.pid("wc", "mazak")
    os.kill(wc, signal.SIGSTOP)  # past 3 s (the run) + 2 s (in_doubt) after the run began: the script decides
    try:
        wait_for(lambda: state(cell, pawn)[0] == "held", 30, "the entity to be held")
        assert "the lot script decides: hold" in lot_log(cell, pawn)
        held = json.loads(ok(gwc(cell, "lots", "--state", "held", "--json")))
        assert [r["entity"] for r in held] == [pawn] and "in doubt, held for the operator" in held[0]["result"], held
        assert "released: reroute" in ok(gwc(cell, "release", str(pawn), "--decision", "reroute"))
        wait_for(lambda: f"held entity {pawn}: reroute" in lot_log(cell, pawn), 10, "the release to reach the lot")
    finally:
        os.kill(wc, signal.SIGCONT)
    import_export_all(cell, [pawn], timeout=60)

    st, reason = state(cell, pawn)  # asked again: wc2, or the Mazak if its woken WC had it Idle first
    assert st == "exported" and re.fullmatch(r"PASS: milled on (wc2|mazak) \(try 2\)", reason or ""), reason
    done = steps(cell, pawn)
    assert len(done) == 2 and done[0]["machines"] == ["mazak"] and not done[0]["runs"]
    assert "in doubt" in done[0]["note"] and "is in doubt" in lot_log(cell, pawn)
    # The woken WC records the run its ME finished: recorded, and counted by nobody a second time.
    wait_for(lambda: outcome(cell, "mazak", run) == [("ACK_OK",)], 20, "the late run to be recorded")
    assert sum(1 for s in steps(cell, pawn) if s["runs"]) == 1


def test_a_run_whose_wc_died_before_announcing_it_counts_from_its_stored_outcome(lot_cell: Any, tmp_path: Path) -> None:
    # The Mazak's WC stores the run's results and outcome, then dies before its Run_Complete goes
    # out: no RUN_COMPL ever comes, but MACHINE_RUN_OUTCOME holds the outcome, so the pawn is not
    # milled a second time on the other mill. The WC announces the run as soon as its commit returns,
    # so the test holds that commit: a deferred trigger sleeps in it, the WC is killed meanwhile, and
    # the server finishes the commit of a client that is gone.
    cell, pawn = milling_on_the_mazak(lot_cell, tmp_path, run_time=4.0)
    run = mazak_run(cell)
    with cell.db() as conn:
        conn.execute(
            "CREATE FUNCTION hold_commit() RETURNS trigger LANGUAGE plpgsql AS $$ BEGIN "
            "PERFORM pg_sleep(3); RETURN NULL; END $$"
        )
        conn.execute(
            "CREATE CONSTRAINT TRIGGER hold_commit AFTER INSERT ON machine_run_outcome DEFERRABLE INITIALLY "
            "DEFERRED FOR EACH ROW WHEN (NEW.machine_id = 'mazak') EXECUTE FUNCTION hold_commit()"
        )
    try:
        wait_for(
            lambda: cell.query(
                "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() AND wait_event = 'PgSleep'"
            )[0][0],
            20,
            "the WC's commit of the outcome, held",
        )
        cell.kill("wc", "mazak")
        wait_for(lambda: outcome(cell, "mazak", run) == [("ACK_OK",)], 20, "the outcome, committed after the WC died")
    finally:
        with cell.db() as conn:
            conn.execute("DROP TRIGGER hold_commit ON machine_run_outcome")
            conn.execute("DROP FUNCTION hold_commit()")
    import_export_all(cell, [pawn], timeout=40)

    st, reason = state(cell, pawn)
    assert st == "exported" and reason == "PASS: milled on mazak (try 1)", reason
    assert [s["machines"] for s in steps(cell, pawn)] == [["mazak"]]
    assert re.search(rf"run {run} on mazak\b.*MACHINE_RUN_OUTCOME says ACK_OK", lot_log(cell, pawn))
    assert cell.query("SELECT count(*) FROM machine_run_result WHERE machine_id = 'wc2'")[0][0] == 0
    assert not cell.log_has("wc:mazak", f"run {run} complete (ACK_OK)"), "its Run_Complete went out after all"
    assert cell.query("SELECT count(*) FROM reserved_machines")[0][0] == 0
