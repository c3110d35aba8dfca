"""The NJIT chess script (thesis Listing 1): measure an aluminium chess set on the CMM.

Like Listing 1 it knows what it needs: op type alum_chess, the machine cmm_wc, the recipe
alum_chess_set. It waits to be imported, asks MSCHED for the CMM, sets up and starts the run,
waits for it, reads the CMM's verdict from MACHINE_RUN_RESULT, gives the CMM back, reports the lot
completed with that verdict, and waits to be exported. A set out of tolerance is still a measured
set: the lot completes with result FAIL (deciding what to do about it is mill_and_measure's job).

A run that failed is not a set that failed: the CMM never measured it (no verdict in time, garbage
on its line, the line lost). The set is measured again, on the CMM once it is back, up to
MEASURE_TRIES times; a set never measured completes NOT MEASURED, never FAIL.
"""

from __future__ import annotations

from gwc.lot import OperationEntity, verdict

OP_TYPE = "alum_chess"
MACHINES = [["cmm_wc"]]  # one alternative: the CMM
RECIPE = "alum_chess_set"
MEASURE_TRIES = 3


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    for attempt in range(1, MEASURE_TRIES + 1):
        op = entity.operate(OP_TYPE, MACHINES, recipes=RECIPE)
        if op.ok:
            break
        entity.log.warning(
            "run %d on %s failed (%s): the set was not measured (try %d of %d)",
            op.machine_run_id,
            op.machines[0],
            ", ".join(f"{r.ack_code}: {r.note}" if r.note else r.ack_code for r in op.runs),
            attempt,
            MEASURE_TRIES,
        )
    where = f"run {op.machine_run_id} on {op.machines[0]}"
    if not op.ok:
        why = "; ".join(r.note for r in op.runs if r.note)
        entity.lot_completed(f"NOT MEASURED: {MEASURE_TRIES} runs failed ({where}{': ' + why if why else ''})")
    else:
        ok, why = verdict(op.results)
        entity.log.info("chess set measured on %s: %s", where, why)
        entity.lot_completed(f"{'PASS' if ok else 'FAIL'}: {why} ({where})")
    entity.wait_for_export()
