"""The NJIT chess script (thesis Listing 1): measure an aluminium chess set on the CMM.

Like Listing 1 it knows what it needs: op type alum_chess, the machine cmm_wc, the recipe
alum_chess_set. It waits to be imported, asks MSCHED for the CMM, sets up and starts the run,
waits for it, reads the CMM's verdict from MACHINE_RUN_RESULT, gives the CMM back, reports the lot
completed with that verdict, and waits to be exported. A set out of tolerance is still a measured
set: the lot completes with result FAIL (deciding what to do about it is mill_and_measure's job).
"""

from __future__ import annotations

from gwc.lot import OperationEntity, verdict

OP_TYPE = "alum_chess"
MACHINES = [["cmm_wc"]]  # one alternative: the CMM
RECIPE = "alum_chess_set"


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    op = entity.operate(OP_TYPE, MACHINES, recipes=RECIPE)
    ok, why = verdict(op.results) if op.ok else (False, "run failed")
    entity.log.info("chess set measured on %s (run %d): %s", ", ".join(op.machines), op.machine_run_id, why)
    entity.lot_completed(f"{'PASS' if ok else 'FAIL'}: {why} (run {op.machine_run_id} on {op.machines[0]})")
    entity.wait_for_export()
