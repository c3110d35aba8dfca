"""The two-machine lot with alternatives (gwc/lot/scripts/mill_and_measure.py), everything real.

Pawns are milled on the Mazak or the second mill (each qualified mill that is up is an
alternative), then measured on the CMM (its simulator's PASS/FAIL pattern is the part's tolerance).
"""

from __future__ import annotations

from typing import Any

from gwc.cell import shutdown
from tests.e2e.lotkit import (
    cell_with_machines,
    gwc,
    holdings,
    import_export_all,
    lot_log,
    ok,
    order,
    state,
    steps,
    wait_state,
)
from tests.harness import CellHarness, wait_for


def machines(pattern: str, mazak_time: float, wc2_time: float) -> list[dict[str, Any]]:
    return [
        {"id": "mazak", "kind": "dummy", "run_time": mazak_time},
        {"id": "wc2", "kind": "dummy", "run_time": wc2_time},
        {
            "id": "cmm_wc",
            "kind": "cmm",
            "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0},
            "sim": {"measure_time": 0.2, "pattern": pattern},
        },
    ]


def status(cell: CellHarness, machine_id: str) -> str:
    return cell.query("SELECT status FROM machine_status WHERE machine_id = %s", machine_id)[0][0]


def test_pawns_go_to_the_other_mill_when_the_mazak_stops_and_are_re_milled_when_out_of_tolerance(lot_cell: Any) -> None:
    # The Mazak is the faster mill: left alone it would take the third pawn. The CMM finds the first
    # pawn it measures out of tolerance (FAIL), the others within (PASS).
    cell = cell_with_machines(lot_cell(machines=machines("FPPPPP", 2.0, 3.0)), "cmm_wc", "mazak", "wc2")
    pawns = order(cell, "milled_pawn=3")
    for e in pawns:
        wait_state(cell, e, "waiting_import")
    ok(gwc(cell, "import", "--all"))
    wait_for(
        lambda: status(cell, "mazak") == "Running" and status(cell, "wc2") == "Running", 20, "both mills to mill a pawn"
    )
    queued = wait_for(lambda: [e for e in pawns if holdings(cell, e)[0]], 15, "the third pawn's request")
    assert holdings(cell, queued[0])[0] == 2, "the third pawn asks for either mill (two alternatives)"
    # The operator stops the Mazak mid-run (as `gwc machine stop mazak` does): it finishes its pawn, then
    # shuts down; the waiting pawn is served by its other alternative.
    assert shutdown(cell.bus, "wc:mazak", "ME_SHUT") == "shut down"
    import_export_all(cell, pawns, timeout=60)

    done = {e: steps(cell, e) for e in pawns}
    mills = {e: [s["machines"][0] for s in st if s["op_type"] == "mill_chess"] for e, st in done.items()}
    assert set(mills[queued[0]]) == {"wc2"}, mills
    assert sum(ms.count("mazak") for ms in mills.values()) == 1, mills
    mazak_runs = cell.query("SELECT count(DISTINCT machine_run_id) FROM machine_run_result WHERE machine_id = 'mazak'")
    assert mazak_runs[0][0] == 1, "MSCHED scheduled a run on the Mazak after it was shut down"
    assert status(cell, "mazak") == "Shutdown"

    re_milled = [e for e, st in done.items() if len(st) == 4]
    assert len(re_milled) == 1, done
    (pawn,) = re_milled
    assert [s["op_type"] for s in done[pawn]] == ["mill_chess", "alum_chess", "mill_chess", "alum_chess"]
    assert [s["runs"][0]["results"]["RESULT"] for s in done[pawn] if s["op_type"] == "alum_chess"] == ["FAIL", "PASS"]
    assert state(cell, pawn)[1].startswith("PASS after 2 milling"), state(cell, pawn)
    assert "re-milling" in lot_log(cell, pawn)
    for e, st in done.items():
        assert state(cell, e)[0] == "exported" and state(cell, e)[1].startswith("PASS"), state(cell, e)
        for step in st:  # each decision was made from MACHINE_RUN_RESULT: the rows are what the script read
            run = step["runs"][0]
            rows = cell.query(
                "SELECT param, value FROM machine_run_result WHERE machine_run_id = %s AND machine_id = %s",
                run["machine_run_id"],
                run["machine_id"],
            )
            assert dict(rows) == run["results"]
