"""A deliberately broken build of the soak's lot script, for the replay test only.

The bug: a lot of priority 30 runs its operation twice. The soak's plan gives priorities from the
seed, so the same seed breaks the same lots, and a replay must find the same ones.
"""

from __future__ import annotations

from gwc.lot.entity import OperationEntity
from gwc.lot.scripts.soak import OP_TYPE, plan_of


def main(entity: OperationEntity) -> None:
    plan = plan_of(entity)
    entity.wait_for_import()
    runs = 2 if plan.get("priority") == 30 else 1
    for _ in range(runs):
        op = entity.operate(plan.get("op_type", OP_TYPE), plan.get("alternatives"), priority=plan.get("priority"))
    entity.lot_completed(f"ran on {', '.join(op.machines)}")
    entity.wait_for_export()
