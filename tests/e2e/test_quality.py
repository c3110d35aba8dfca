"""Quality end to end (docs/quality.md): a simulated mill with a process, the CMM simulator measuring
each part's features over its serial line, the values stored as numbers with the runs, the verdict
from the recipe's tolerances, and SPC's alarm on a step shift, all in one private cell."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from tests.e2e.lotkit import cell_with_machines, gwc, import_export_all, ok, order, state
from tests.harness import CellHarness

FEATURES = "FEATURE DIAMETER 25.00 0.05\nFEATURE HEIGHT 40.00 0.10\n"
SIGMA = 0.005  # the mill's noise on DIAMETER: the step shift is 2 sigma


def quality_machines(process: dict[str, Any]) -> list[dict[str, Any]]:
    return [
        {"id": "mazak", "kind": "dummy", "run_time": 0.05, "process": process},
        {
            "id": "cmm_wc",
            "kind": "cmm",
            "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0},
            "sim": {"measure_time": 0.05, "gauge_sigma": 0.0005, "seed": 3},
        },
    ]


def add_recipe(cell: CellHarness, tmp: Path, recipe_id: str, body: str) -> None:
    path = tmp / f"{recipe_id}.txt"
    path.write_text(body)
    ok(gwc(cell, "recipe", "add", recipe_id, str(path), "--approve"))


def test_features_are_measured_stored_and_a_two_sigma_step_shift_is_alarmed_within_10_parts(
    lot_cell: Any, tmp_path: Path
) -> None:
    process = {"seed": 11, "sigma": {"DIAMETER": SIGMA, "HEIGHT": 0.01}, "shift": {"after": 10, "DIAMETER": 2 * SIGMA}}
    cell = lot_cell(machines=quality_machines(process), sections={"quality": {"spc_baseline": 10}})
    cell = cell_with_machines(cell, "cmm_wc", "mazak")
    add_recipe(cell, tmp_path, "mill_pawn", "# mill_pawn v2\nPROFILE pawn\n" + FEATURES)
    add_recipe(cell, tmp_path, "alum_chess_set", "# alum_chess_set v2: CMM part program\nPART pawn\n" + FEATURES)
    pawns = order(cell, "milled_pawn=20")
    import_export_all(cell, pawns, timeout=120)

    # Every part measured: each feature's value a number with its measuring run, the part's milling named.
    rows = cell.query(
        "SELECT m.machine_run_id, m.feature, m.measured, m.in_tol, mk.machine_id, mk.offset_used, r.value "
        "FROM run_features m JOIN run_features mk ON mk.machine_run_id = m.workpiece AND mk.feature = m.feature "
        "JOIN machine_run_result r ON r.machine_run_id = m.machine_run_id AND r.machine_id = m.machine_id "
        "AND r.param = m.feature WHERE m.machine_id = 'cmm_wc'"
    )
    assert len(rows) == 2 * len(pawns), rows
    for _run, feature, measured, in_tol, maker, offset, text in rows:
        assert maker == "mazak" and offset == 0.0
        assert abs(measured - float(text)) < 1e-9, "the number stored is the value the CMM sent"
        nominal = 25.0 if feature == "DIAMETER" else 40.0
        assert in_tol == (abs(measured - nominal) <= (0.05 if feature == "DIAMETER" else 0.10))
    for e in pawns:  # the verdict came from the tolerances
        st, reason = state(cell, e)
        assert st == "exported" and reason is not None and "within tolerance: DIAMETER" in reason, (e, reason)

    # The shift (from the mill's 11th part on) is alarmed by SPC within 10 parts, before any part fails.
    alarms = cell.query("SELECT alarm_text FROM alarms WHERE alarm_id = 'SPC_RULE' AND machine_id = 'mazak'")
    diameter = [t for (t,) in alarms if " DIAMETER " in t]
    assert diameter, alarms
    at = int(re.search(r"at part (\d+)", diameter[0]).group(1))  # type: ignore[union-attr]
    assert 10 < at <= 20, diameter
    assert all(r[3] for r in rows), "a 2 sigma shift leaves the parts in tolerance"

    # `gwc spc` shows the chart, the rule and Cpk.
    out = ok(gwc(cell, "spc", "--machine", "mazak", "--feature", "DIAMETER"))
    assert "DIAMETER" in out and "Cpk" in out and "WE" in out, out
