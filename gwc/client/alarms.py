"""Alarms and the status line: the alarm history (read), clearing one through the Cell Alarm Server
(ALARM_CLR_REQ: the table's one writer, which then tells the waiting WC), and the operator's status line
from the Status Line Server (STATUS_LN)."""

from __future__ import annotations

from typing import Any

import psycopg

from gwc.client.session import ANSWER, ask, operator
from gwc.errors import Refused
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg

STATUS_LINE_FIELDS = ("text", "imports", "exports", "alarms", "last_event")

__all__ = ["STATUS_LINE_FIELDS", "alarm_rows", "clear_alarm", "describe_alarm", "description_rows", "read_status_line"]


def alarm_rows(conn: psycopg.Connection[Any], show_all: bool = False) -> list[dict[str, Any]]:
    """Pending alarms (oldest first), or the whole history, times as text; an alarm_id not in
    ALARM_DESCRIPTION is marked "(unknown)". On the caller's connection (a screen keeps one open)."""
    cur = conn.execute(
        "select alarm_no, alarm_id, known, machine_id, alarm_text, raised_by, raised_at, cleared_by, cleared_at, "
        "actions_taken "
        "from alarms" + ("" if show_all else " where cleared_at is null") + " order by alarm_no"
    )
    names = [d.name for d in cur.description or []]
    rows = [dict(zip(names, r)) for r in cur.fetchall()]
    conn.rollback()
    for r in rows:
        r["alarm_id"] = r["alarm_id"] if r["known"] else f"{r['alarm_id']} (unknown)"
        for k in ("raised_at", "cleared_at"):
            r[k] = r[k].strftime("%Y-%m-%d %H:%M:%S") if r[k] else None
    return rows


def clear_alarm(bus: BlockingBus, alarm_no: int, by: str | None = None, timeout: float = ANSWER) -> Message:
    """ALARM_CLR_REQ to the Cell Alarm Server: the machine waiting on the alarm continues. Returns its
    Alarm_Clear_Ack; Refused if the CAS says no (unknown or already cleared)."""
    ack = ask(
        bus,
        Conv.ALARM_CLR_REQ,
        message(Msg.ALARM_CLEAR_REQUEST, alarm_no=alarm_no, cleared_by=by or operator()),
        "cas",
        timeout,
    )
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or "")
    return ack


def describe_alarm(
    bus: BlockingBus,
    alarm_id: str,
    text: str | None = None,
    severity: str | None = None,
    actions: list[str] | None = None,
    timeout: float = ANSWER,
) -> str:
    """ALARM_DESC to the Cell Alarm Server (the table's one writer): add or change an alarm's description
    and what the CAS does for it (actions: shutdown, page; [] for none; None leaves them). Returns the
    description as it is now; Refused if the CAS says no."""
    ack = ask(
        bus,
        Conv.ALARM_DESC,
        message(
            Msg.ALARM_DESCRIBE, alarm_id=alarm_id, alarm_text=text, severity=severity, actions=actions, by=operator()
        ),
        "cas",
        timeout,
    )
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or "")
    return str(ack.note or "")


def description_rows(conn: psycopg.Connection[Any]) -> list[dict[str, Any]]:
    """ALARM_DESCRIPTION: every alarm the cell knows, its severity and the CAS's actions for it."""
    cur = conn.execute("select alarm_id, severity, actions, alarm_text from alarm_description order by alarm_id")
    rows = [
        {"alarm_id": a, "severity": sev, "actions": ",".join(act) or "-", "alarm_text": t}
        for a, sev, act, t in cur.fetchall()
    ]
    conn.rollback()
    return rows


def read_status_line(bus: BlockingBus, timeout: float = ANSWER) -> Message:
    """STATUS_LN to the Status Line Server: lots waiting for import or export, pending alarms, the last
    event (fields STATUS_LINE_FIELDS; `text` is the line as shown)."""
    return ask(bus, Conv.STATUS_LN, message(Msg.STATUS_LINE_GET), "sls", timeout)
