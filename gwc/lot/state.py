"""The operation entity's own state: who it is, what the Lot Server said of it, the script's settings,
and its traveller (see gwc/lot/entity.py). Every part of the entity holds the one EntityState."""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Any, Generic, TypeVar, overload

from gwc.config import Config
from gwc.lot.model import Reservation, Run, Timeouts, now_text, save_traveller

V = TypeVar("V")


@dataclass
class EntityState:
    """One entity's facts and settings, shared by its parts (the lot script reads and sets them through
    OperationEntity's attributes of the same names)."""

    cfg: Config
    entity_id: int
    log: logging.Logger
    timeouts: Timeouts = field(default_factory=Timeouts)
    max_tries: int = 3
    # What the lot script decides for a run in doubt past its bound (runs.py): "hold" (the safe
    # default for a physical part: the entity stops, failed with the reason) or "reroute".
    in_doubt: str = "hold"
    lot_id: int | None = None
    state: str | None = None
    product_id: str | None = None
    priority: int | None = None
    work_order_id: int | None = None
    script_id: str | None = None  # LOT_SCRIPTS' row for the lot (read with it at open)
    script_path: str | None = None
    result: str | None = None
    failed: bool = False  # fail() ran (or the attach was refused): nothing more to clean up
    traveller: dict[str, Any] = field(default_factory=dict)
    # Where the traveller is kept besides its file: the database, in a cell whose lot scripts outlive
    # their host (gwc/lothosts.py's TravellerStore); None on one host.
    keep: Any = None

    def __post_init__(self) -> None:
        self.entity_id = int(self.entity_id)
        self.traveller = self.traveller or {"entity_id": self.entity_id, "steps": []}

    @property
    def name(self) -> str:
        """The entity's name on the bus."""
        return f"lot:{self.entity_id}"

    def set_state(self, state: str) -> None:
        self.state = state
        self.traveller["state"] = str(state)

    def record(self, op_type: str, res: Reservation, runs: list[Run], note: str) -> None:
        """One step of the traveller: what ran where, and what the entity made of it."""
        self.traveller["steps"].append(
            {
                "op_type": op_type,
                "machine_run_id": res.machine_run_id,
                "request_key": res.request_key,
                "machines": res.machines,
                "runs": [asdict(r) for r in runs],
                "note": note,
                "at": now_text(),
            }
        )
        self.save()

    def save(self) -> None:
        """Write the traveller (var/lots/entity-E.json) whole, and in a hosted cell into LOT_TRAVELLERS."""
        try:
            save_traveller(self.cfg, self.entity_id, self.traveller)
        except OSError as e:
            self.log.warning("could not write the traveller: %s", e)
        if self.keep is not None:  # the record a script on another host resumes from
            self.keep.save(self.traveller)


class Shared(Generic[V]):
    """An attribute of OperationEntity that is its EntityState's (or another part's) field of the same
    name: `entity.timeouts = ...` sets what every part reads."""

    def __init__(self, part: str = "facts", name: str = "") -> None:
        self.part = part
        self.name = name

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = self.name or name

    @overload
    def __get__(self, obj: None, owner: type) -> Shared[V]: ...
    @overload
    def __get__(self, obj: object, owner: type) -> V: ...
    def __get__(self, obj: object | None, owner: type) -> Shared[V] | V:
        if obj is None:
            return self
        value: V = getattr(getattr(obj, self.part), self.name)
        return value

    def __set__(self, obj: object, value: V) -> None:
        setattr(getattr(obj, self.part), self.name, value)
