"""The Cell Alarm Server's database side: every read and write of ALARMS and ALARM_DESCRIPTION its
handlers make (gwc/servers/alarm.py parses, takes the alarms' actions, broadcasts and answers).

Each function takes the cursor of one transaction or returns a one-statement `Statement`, returns a
dataclass, and raises `Refused` with the ack code and the reason when the request does not fit the
tables. A refusal rolls the step back: nothing it did is kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gwc import db
from gwc.db import Statement
from gwc.errors import Refused
from gwc.ipc.codes import AckCode


@dataclass(frozen=True)
class Recorded:
    """An alarm as recorded: its number, whether ALARM_DESCRIPTION knows it, its text (given, or the
    description's), and the actions its description asks of the CAS."""

    alarm_no: int
    known: bool
    text: str
    actions: tuple[str, ...]


@dataclass(frozen=True)
class Described:
    """An alarm's description after ALARM_DESC."""

    alarm_text: str
    severity: str
    actions: tuple[str, ...]


@dataclass(frozen=True)
class Cleared:
    """A pending alarm cleared: what ALARM_CLEAR tells the cell."""

    alarm_id: str
    machine_id: str | None


def pending() -> Statement:
    """How many alarms are pending."""
    return Statement("select count(*) from alarms where cleared_at is null", into=lambda row: int(row[0]))


def record(cur: Any, alarm_id: str, text: str | None, machine_id: str | None, raised_by: str) -> Recorded:
    """A new alarm, numbered (ALARM_NO), known or not: an alarm the description table does not know is
    recorded all the same, marked unknown."""
    row = cur.execute("select alarm_text, actions from alarm_description where alarm_id = %s", (alarm_id,)).fetchone()
    known = row is not None
    full = text or (row[0] if known else f"unknown alarm {alarm_id}")
    no = db.get_new_max_value(cur, "ALARM_NO")
    cur.execute(
        "insert into alarms (alarm_no, alarm_id, known, machine_id, alarm_text, raised_by) "
        "values (%s, %s, %s, %s, %s, %s)",
        (no, alarm_id, known, machine_id, full, raised_by),
    )
    return Recorded(no, known, full, tuple(row[1]) if known else ())


def actions_taken(alarm_no: int, taken: str) -> Statement:
    """What the CAS did for an alarm, kept in ALARMS.actions_taken."""
    return Statement("update alarms set actions_taken = %s where alarm_no = %s", (taken, alarm_no), None)


def describe(alarm_id: str, text: str | None, severity: str | None, actions: list[str] | None) -> Statement:
    """An alarm's description added, or changed in what is given."""
    return Statement(
        "insert into alarm_description (alarm_id, alarm_text, severity, actions) "
        "values (%(id)s, coalesce(%(text)s, %(id)s), coalesce(%(sev)s, 'warning'), "
        "coalesce(%(act)s, '{}'::text[])) on conflict (alarm_id) do update set "
        "alarm_text = coalesce(%(text)s, alarm_description.alarm_text), "
        "severity = coalesce(%(sev)s, alarm_description.severity), "
        "actions = coalesce(%(act)s, alarm_description.actions) "
        "returning alarm_text, severity, actions",
        {"id": alarm_id, "text": text, "sev": severity, "act": actions},
        into=lambda row: Described(row[0], row[1], tuple(row[2])),
    )


def clear(cur: Any, alarm_no: int, cleared_by: str) -> Cleared:
    """A pending alarm cleared by the operator. Refused UNKNOWN (no such alarm), NOTNOW (cleared before:
    by whom and when)."""
    row = cur.execute(
        "select alarm_id, machine_id, cleared_by, cleared_at from alarms where alarm_no = %s for update", (alarm_no,)
    ).fetchone()
    if row is None:
        raise Refused(AckCode.UNKNOWN, f"no alarm number {alarm_no}")
    alarm_id, machine_id, by, at = row
    if at is not None:
        raise Refused(AckCode.NOTNOW, f"alarm {alarm_no} was already cleared by {by} at {at:%Y-%m-%d %H:%M:%S}")
    cur.execute("update alarms set cleared_by = %s, cleared_at = now() where alarm_no = %s", (cleared_by, alarm_no))
    return Cleared(alarm_id, machine_id)
