"""The soak's lot: one operation on one machine, or on the first of its alternatives MSCHED can give.

The chaos soak (gwc.soak) orders a stream of these. Which machines a lot may use, and its priority,
the soak decides from its seed and leaves for the script in <var>/soak/lot-<lot_id>.json before
starting it; without that file the lot takes any machine qualified for the operation that is up,
as an operator's own order of this product would. With a plan, the script leaves how long its
operation took (request to unreserve) and its named events (gwc/lot/events.py) in
<var>/soak/timing-<entity>.json for `gwc bench cell`.
Everything else is the ordinary life of a lot (Listing 1): wait to be imported, operate,
complete, wait to be exported.
"""

from __future__ import annotations

import json
import time

from gwc.lot import events
from gwc.lot.entity import OperationEntity

OP_TYPE = "dummy_op"


def plan_of(entity: OperationEntity) -> dict:
    """The soak's plan for this lot, or {} when the lot was ordered some other way."""
    try:
        return json.loads((entity.cfg.var / "soak" / f"lot-{entity.lot_id}.json").read_text())
    except (OSError, ValueError):
        return {}


def main(entity: OperationEntity) -> None:
    plan = plan_of(entity)
    entity.wait_for_import()
    marks = events.record(entity.log)  # the operation's named events (gwc/lot/events.py), for the timing file
    began, cpu = time.monotonic(), time.process_time()
    op = entity.operate(plan.get("op_type", OP_TYPE), plan.get("alternatives"), priority=plan.get("priority"))
    took, cpu = time.monotonic() - began, time.process_time() - cpu
    if plan:  # what `gwc bench cell` reads: the whole operation, request to unreserve, as the script saw it
        timing = entity.cfg.var / "soak" / f"timing-{entity.entity_id}.json"
        timing.write_text(
            json.dumps(
                {
                    "operate_s": took,
                    "operate_cpu_s": cpu,
                    "tries": op.tries,
                    "machines": op.machines,
                    "events": marks.as_list(),
                }
            )
        )
    entity.lot_completed(
        f"ran {op.op_type} on {', '.join(op.machines)} (run {op.machine_run_id}, try {op.tries}): "
        + ("ok" if op.ok else "run failed")
    )
    entity.wait_for_export()
