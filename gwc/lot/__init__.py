"""gwc.lot: the operation-entity library lot scripts are written with (see gwc/lot/entity.py, docs/lot-scripts.md)."""

from gwc.lot.entity import (
    MachineRequest,
    Operation,
    OperationEntity,
    Reservation,
    Run,
    Timeouts,
    create_lot,
    read_traveller,
    traveller_path,
    verdict,
)
from gwc.lot.errors import (
    LotError,
    LotTimeout,
    MachineDied,
    MachineLost,
    RequestCancelled,
    RequestRefused,
    RunFailed,
    RunInDoubt,
    ScriptStopped,
    StepRefused,
)

__all__ = [
    "LotError",
    "LotTimeout",
    "MachineDied",
    "MachineLost",
    "MachineRequest",
    "Operation",
    "OperationEntity",
    "RequestCancelled",
    "RequestRefused",
    "Reservation",
    "Run",
    "RunFailed",
    "RunInDoubt",
    "ScriptStopped",
    "StepRefused",
    "Timeouts",
    "create_lot",
    "read_traveller",
    "traveller_path",
    "verdict",
]
