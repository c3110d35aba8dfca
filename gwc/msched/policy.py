"""MSCHED's scheduling policy: the one function that decides who goes first (thesis 3.5).

The scheduling pass (sql msched_pass, called by gwc.msched.store) finds every queued request that
could be bound right now, taken alone, and binds them greedily in the policy's order, skipping a
request whose machines an earlier one took. The pass runs in the database, so it sorts by the rank
each request was given when queued (`rank_sql`, then arrival); `order` is the same order in Python
(for tests and tools). Changing how the cell schedules is writing that pair; etc/cell.toml
`[cell] policy` chooses which.

* fifo: oldest first (the thesis's algorithm, 6.2.4.6), by arrival order `seq`.
* priority: the lot's priority first (lower number = more urgent, the seed's default is 20), with
  ageing: every `ageing_s` seconds a request has waited counts as one step more urgent, so an old
  request always overtakes, in the end, a stream of newer, more urgent ones (nothing starves).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Protocol

from gwc.config import Config
from gwc.errors import ConfigError

DEFAULT_AGEING_S = 30.0


@dataclass(frozen=True)
class Candidate:
    """A queued request whose machines are all up, free and accepting its op type."""

    request_key: int
    entity_id: int
    op_type: str
    priority: int
    seq: int  # arrival order
    requested_at: datetime
    machines: tuple[str, ...]


class Policy(Protocol):
    name: str

    def order(self, candidates: Sequence[Candidate], now: datetime) -> list[Candidate]:
        """The candidates in the order they should be bound."""
        ...

    def rank_sql(self) -> str:
        """The same order as an SQL expression over a request's `priority` and `requested_at`.

        Stored with the request when it is queued (request_machines.rank; ties go by arrival, seq),
        so the pass walks the index (machine_id, rank, seq) and fetches, per freed machine, the first
        few candidates in the order `order` will put them. It must sort exactly as `order` does.
        """
        ...


class Fifo:
    """First in, first out: the thesis's fair and simple choice."""

    name = "fifo"

    def order(self, candidates: Sequence[Candidate], now: datetime) -> list[Candidate]:
        return sorted(candidates, key=lambda c: c.seq)

    def rank_sql(self) -> str:
        return "0"


class Priority:
    """The most urgent (lowest effective priority) first; ageing keeps the oldest from starving."""

    name = "priority"

    def __init__(self, ageing_s: float = DEFAULT_AGEING_S) -> None:
        if ageing_s <= 0:
            raise ConfigError(f"msched.ageing_s must be > 0, got {ageing_s}")
        self.ageing_s = ageing_s

    def effective(self, c: Candidate, now: datetime) -> float:
        waited = max(0.0, (now - c.requested_at).total_seconds())
        return c.priority - waited / self.ageing_s

    def order(self, candidates: Sequence[Candidate], now: datetime) -> list[Candidate]:
        return sorted(candidates, key=lambda c: (self.effective(c, now), c.seq))

    def rank_sql(self) -> str:
        # effective = priority - (now - requested_at) / ageing_s; `now` is the same for all, so drop it.
        return f"priority + extract(epoch from requested_at) / {self.ageing_s!r}"


def make_policy(cfg: Config) -> Policy:
    """The policy etc/cell.toml chooses ([cell] policy; [msched] ageing_s for priority)."""
    if cfg.policy == "priority":
        return Priority(float(cfg.raw.get("msched", {}).get("ageing_s", DEFAULT_AGEING_S)))
    return Fifo()
