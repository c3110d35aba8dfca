"""A lot script a user writes and registers, run for real; its mill dies mid-run and it carries on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tests.e2e.lotkit import (cell_with_machines, gwc, import_export_all, lot_cell, lot_log, ok, order,  # noqa: F401
                              start_machine, state, steps, wait_state)
from tests.harness import wait_for

SCRIPT = '''"""Mill a bare pawn: no measuring."""

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    op = entity.operate("mill_chess")
    entity.lot_completed(f"PASS: milled on {op.machines[0]} (try {op.tries})")
    entity.wait_for_export()
'''


def test_registered_script_asks_again_when_its_machine_dies_mid_run(lot_cell: Any, tmp_path: Path) -> None:
    cell = cell_with_machines(lot_cell(machines=[
        {"id": "mazak", "kind": "dummy", "run_time": 30.0, "liveness": 1.0},
        {"id": "wc2", "kind": "dummy", "run_time": 0.3},
    ]), "mazak")
    script = tmp_path / "bare_pawn.py"
    script.write_text(SCRIPT)
    ok(gwc(cell, "script", "register", "bare_pawn", str(script), "--product", "bare_pawn"))
    (pawn,) = order(cell, "bare_pawn=1")
    wait_state(cell, pawn, "waiting_import")
    ok(gwc(cell, "import", str(pawn)))
    wait_for(lambda: cell.query("SELECT status FROM machine_status WHERE machine_id = 'mazak'")[0][0] == "Running",
             20, "the Mazak to mill")
    start_machine(cell, "wc2")
    cell.kill("wc", "mazak")  # the Mazak's WC dies mid-run: the Machine Server marks it Shutdown (liveness)
    import_export_all(cell, [pawn], timeout=40)

    st, reason = state(cell, pawn)
    assert st == "exported" and reason == "PASS: milled on wc2 (try 2)", reason
    done = steps(cell, pawn)
    assert [s["machines"] for s in done] == [["mazak"], ["wc2"]]
    assert done[0]["note"].startswith("machine lost: mazak")
    assert "unreserving and asking again" in lot_log(cell, pawn)
    assert cell.query("SELECT count(*) FROM reserved_machines")[0][0] == 0
