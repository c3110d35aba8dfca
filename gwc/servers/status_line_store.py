"""The Status Line Server's database side: what waits for the operator, read from the owners' tables
(the Lot Server's LOT_STATUS, the Cell Alarm Server's ALARMS) at every STATUS_LN. The server writes
nothing (role gwc_sls reads only): gwc/servers/status_line.py puts the line together and answers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Alarm:
    """The newest pending alarm."""

    alarm_no: int
    text: str
    known: bool


@dataclass(frozen=True)
class Waiting:
    """What waits for the operator: entities to import and to export, pending alarms and the newest."""

    imports: list[int]
    exports: list[int]
    alarms: int
    newest: Alarm | None


def waiting(cur: Any) -> Waiting:
    """One snapshot of what waits (one transaction: the counts agree with each other)."""
    by_state = dict(
        cur.execute(
            "select s.state, array_agg(s.entity_id order by s.entity_id) from lot_status s "
            "join lot_entities e using (entity_id) where e.destroyed_at is null "
            "and s.state in ('waiting_import', 'waiting_export') group by s.state"
        ).fetchall()
    )
    pending = cur.execute("select count(*) from alarms where cleared_at is null").fetchone()[0]
    newest = cur.execute(
        "select alarm_no, alarm_text, known from alarms where cleared_at is null order by alarm_no desc limit 1"
    ).fetchone()
    return Waiting(
        list(by_state.get("waiting_import", [])),
        list(by_state.get("waiting_export", [])),
        int(pending),
        None if newest is None else Alarm(*newest),
    )
