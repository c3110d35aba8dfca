"""Mill a pawn, then measure it; re-mill a part out of tolerance, scrap it after too many tries.

Thesis 1.3's plan for the NJIT cell: "the Mazak will mill chess pieces and the CMM will measure
them to see if the pieces are within an acceptable tolerance. If not, they will either be sent back
to be re-milled or discarded as scrap." Two operations, each on any machine qualified for it that
is up (alternatives: the Mazak, or another mill): if a mill shuts down while the lot waits, MSCHED
serves it from the other alternative; if it shuts down mid-run, the step is asked again. The
tolerance decision is made from the measuring run's MACHINE_RUN_RESULT (thesis 3.2.3).

Where the mill's recipe declares FEATUREs (docs/quality.md), each milling carries a run sheet: the
offsets of the run-to-run feedback (a recipe with FEEDBACK), and for a re-milling the correction the
part's own measurement asks for (feed forward); the measurement names the part it measures, the
verdict follows from the measured features' tolerances, and the mill's control charts are checked
(SPC_RULE) after each first measurement. The mills are asked for best yield first (6.1: "machine M1
is better than M2"): when both are free the better one mills the part.
"""

from __future__ import annotations

from gwc.lot import OperationEntity, verdict
from gwc.quality.lot import Quality

MILL = "mill_chess"
MEASURE = "alum_chess"
MAX_MILLS = 3  # the first milling and up to two re-millings; then the part is scrap


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    quality = Quality(entity)
    result = ""
    made = measured = None  # the last milling and its measurement: a re-milling works on that part
    for attempt in range(1, MAX_MILLS + 1):
        mill = entity.operate(MILL, quality.preferred(MILL), sheet=quality.mill_sheet(remill=made, measured=measured))
        if not mill.ok:
            entity.log.warning(
                "milling run %d on %s failed (%s): milling again",
                mill.machine_run_id,
                mill.machines[0],
                "; ".join(r.note for r in mill.runs if r.note) or "no reason recorded",
            )
            result = f"milling failed on {mill.machines[0]}"
            continue
        for _ in range(MAX_MILLS):  # a measuring run that failed measured nothing: measure again, not mill
            measure = entity.operate(MEASURE, sheet=quality.measure_sheet(mill))
            if measure.ok:
                break
            entity.log.warning(
                "measuring run %d failed (%s): the part was not measured",
                measure.machine_run_id,
                "; ".join(r.note for r in measure.runs if r.note) or "no reason recorded",
            )
        from_features = quality.verdict(measure) if measure.ok else None
        if from_features is not None and made is None:
            quality.check_spc(mill)  # the first milling's part only: a re-milled part is not the process's
        ok, why = from_features or (verdict(measure.results) if measure.ok else (False, "measuring runs failed"))
        entity.log.info(
            "mill %d on %s (run %d), measured on %s (run %d): %s",
            attempt,
            mill.machines[0],
            mill.machine_run_id,
            measure.machines[0],
            measure.machine_run_id,
            why,
        )
        if ok:
            result = f"PASS after {attempt} milling(s): milled on {mill.machines[0]}, {why}"
            break
        result = f"{why} after milling {attempt} on {mill.machines[0]}"
        made, measured = mill, measure
        if attempt < MAX_MILLS:
            entity.log.warning("part out of tolerance: re-milling (%d of %d)", attempt + 1, MAX_MILLS)
    else:
        result = f"SCRAP: {result}"
        entity.log.warning("part scrapped: %s", result)
        entity.scrap(mill.machines[0], mill.machine_run_id, 1, result)  # the mill's books (1.4.2)
    entity.lot_completed(result)
    entity.wait_for_export()
