"""A lot script a user writes and registers, run for real; its mill dies mid-run, or after the run but
before announcing it, and it carries on."""

from __future__ import annotations

import os
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

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    op = entity.operate("mill_chess")
    entity.lot_completed(f"PASS: milled on {op.machines[0]} (try {op.tries})")
    entity.wait_for_export()
'''


def milling_on_the_mazak(lot_cell: Any, tmp_path: Path, run_time: float) -> tuple[Any, int]:
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
    script.write_text(SCRIPT)
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


def test_registered_script_asks_again_when_its_machine_dies_mid_run(lot_cell: Any, tmp_path: Path) -> None:
    cell, pawn = milling_on_the_mazak(lot_cell, tmp_path, run_time=30.0)
    cell.kill("wc", "mazak")  # the Mazak's WC dies mid-run: the Machine Server marks it Shutdown (liveness)
    import_export_all(cell, [pawn], timeout=40)

    st, reason = state(cell, pawn)
    assert st == "exported" and reason == "PASS: milled on wc2 (try 2)", reason
    done = steps(cell, pawn)
    assert [s["machines"] for s in done] == [["mazak"], ["wc2"]]
    assert done[0]["note"].startswith("machine lost: mazak")
    assert "unreserving and asking again" in lot_log(cell, pawn)
    assert cell.query("SELECT count(*) FROM reserved_machines")[0][0] == 0


def test_a_run_whose_wc_died_before_announcing_it_counts_from_its_stored_outcome(lot_cell: Any, tmp_path: Path) -> None:
    # The Mazak's WC stores the run's results and outcome, then dies before its Run_Complete goes
    # out: no RUN_COMPL ever comes, but MACHINE_RUN_OUTCOME holds the outcome, so the pawn is not
    # milled a second time on the other mill.
    cell, pawn = milling_on_the_mazak(lot_cell, tmp_path, run_time=4.0)
    ms = cell.pid("ms")
    assert ms is not None
    os.kill(ms, signal.SIGSTOP)  # the Machine Server holds the WC's change to Idle until it is dead
    try:
        ((status, run),) = cell.query("SELECT status, machine_run_id FROM machine_status WHERE machine_id = 'mazak'")
        assert status == "Running", "the run ended before the Machine Server was stopped: the test proves nothing"
        wait_for(
            lambda: (
                cell.query(
                    "SELECT ack_code FROM machine_run_outcome WHERE machine_id = 'mazak' AND machine_run_id = %s", run
                )
                == [("ACK_OK",)]
            ),
            20,
            "the run's stored outcome",
        )
        cell.kill("wc", "mazak")
    finally:
        os.kill(ms, signal.SIGCONT)
    import_export_all(cell, [pawn], timeout=40)

    st, reason = state(cell, pawn)
    assert st == "exported" and reason == "PASS: milled on mazak (try 1)", reason
    assert [s["machines"] for s in steps(cell, pawn)] == [["mazak"]]
    assert f"run {run} on mazak: no RUN_COMPL came, MACHINE_RUN_OUTCOME says ACK_OK" in lot_log(cell, pawn)
    assert cell.query("SELECT count(*) FROM machine_run_result WHERE machine_id = 'wc2'")[0][0] == 0
    assert not cell.log_has("wc:mazak", f"run {run} complete (ACK_OK)"), "its Run_Complete went out after all"
    assert cell.query("SELECT count(*) FROM reserved_machines")[0][0] == 0
