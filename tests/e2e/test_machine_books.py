"""The Machine Server's books (1.4.2), on a real cell: runs since maintenance and the parts a lot's verdict
scraps on the machine status screen, maintenance due, and `gwc machine maintenance-done`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from gwc.client.machines import machine_rows
from tests.e2e.lotkit import cell_with_machines, gwc, import_export_all, ok, order, state
from tests.harness import wait_for

SCRIPT = '''"""Mill two pawns on wc1; the first is scrap by the lot's verdict (reported twice: counted once)."""

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    first = entity.operate("mill_chess", [["wc1"]])
    entity.scrap("wc1", first.machine_run_id, 1, "SCRAP: out of tolerance")
    entity.scrap("wc1", first.machine_run_id, 1, "SCRAP: out of tolerance")
    entity.operate("mill_chess", [["wc1"]])
    entity.lot_completed("PASS: one of two")
    entity.wait_for_export()
'''


def books(cell: Any) -> dict[str, Any]:
    """wc1's row of the status screen, as `gwc machine status --json` reads it (read here: each `gwc`
    costs a fresh interpreter; the command itself is run once below)."""
    with cell.db() as conn:
        return next(r for r in machine_rows(conn, cell.cfg, set()) if r["machine_id"] == "wc1")


@pytest.mark.soak  # ~40 s at load 10: a lot of two millings and six `gwc` commands (suite budget)
def test_the_status_screen_shows_runs_and_the_lots_scrap_and_maintenance_done_restarts_the_count(
    lot_cell: Any, tmp_path: Path
) -> None:
    machines = [{"id": "wc1", "kind": "dummy", "run_time": 0.2, "maintenance_every": 2}]
    cell = cell_with_machines(lot_cell(machines=machines), "wc1")
    (tmp_path / "two.py").write_text(SCRIPT)
    ok(gwc(cell, "script", "register", "two", str(tmp_path / "two.py"), "--product", "two_pawns"))
    (lot,) = order(cell, "two_pawns=1")
    import_export_all(cell, [lot], timeout=40)
    assert state(cell, lot) == ("exported", "PASS: one of two")

    seen = books(cell)
    assert (seen["runs"], seen["maint_every"], seen["scrap"]) == (2, 2, 1), seen
    listed = json.loads(ok(gwc(cell, "machine", "status", "--json")))
    assert [(r["runs"], r["maint_every"], r["scrap"]) for r in listed] == [(2, 2, 1)]
    wait_for(
        lambda: cell.query("SELECT 1 FROM alarms WHERE alarm_id = 'MAINT_DUE' AND machine_id = 'wc1'"),
        10,
        "maintenance due after 2 runs",
    )
    assert "wc1 maintained after 2 run(s)" in ok(gwc(cell, "machine", "maintenance-done", "wc1"))
    assert (books(cell)["runs"], books(cell)["scrap"]) == (0, 1)
    unknown = gwc(cell, "machine", "maintenance-done", "nosuch")
    assert unknown.returncode != 0 and "unknown machine 'nosuch'" in unknown.stderr
    assert cell.query("SELECT entity_id, parts FROM scrap_reports") == [(lot, 1)]
