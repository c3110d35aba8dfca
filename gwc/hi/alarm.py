"""Alarms and the status line: `gwc alarm list`, `gwc alarm clear`, `gwc status-line`.

The list is read from the alarm history (reads are free); clearing goes through the Cell Alarm
Server (ALARM_CLR_REQ), the table's one writer, which then tells the waiting WC (ALARM_CLEAR). The
status line is asked of the Status Line Server (STATUS_LN), as every HI screen of 7.4 shows it.
"""

from __future__ import annotations

import getpass
import json
import os
from typing import Any

import click
import psycopg

from gwc import db
from gwc.cell import hi_bus
from gwc.errors import Refused
from gwc.hi import context, json_option, table
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode

TIMEOUT = 10.0


def operator() -> str:
    """Who the HI acts for, as the alarm history records it."""
    return f"{getpass.getuser()}@hi.{os.getpid()}"


@click.group("alarm")
def alarm_group() -> None:
    """The cell's alarms (Cell Alarm Server)."""


@alarm_group.command("list")
@click.option("--all", "show_all", is_flag=True, help="The whole history, not only the pending alarms.")
@json_option
def alarm_list(show_all: bool, as_json: bool) -> None:
    """Pending alarms (oldest first), or the whole history with --all."""
    cfg, log = context()
    with db.connect(cfg, role="hi", log=log) as conn:
        rows = alarm_rows(conn, show_all)
    columns = ["alarm_no", "alarm_id", "machine_id", "alarm_text", "raised_by", "raised_at"]
    table(rows, columns + (["cleared_by", "cleared_at"] if show_all else []), as_json)


@alarm_group.command("clear")
@click.argument("alarm_no", type=int)
@click.option("--by", default=None, help="Who clears it (default: user@hi.pid).")
def alarm_clear(alarm_no: int, by: str | None) -> None:
    """Clear a pending alarm: the machine waiting on it continues."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        ack = clear_alarm(bus, alarm_no, by or operator())
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or "")
    click.echo(f"alarm {alarm_no} cleared")


@click.command("status-line")
@json_option
def status_line(as_json: bool) -> None:
    """The operator's status line: lots waiting for import or export, pending alarms, the last event."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        line = read_status_line(bus)
    if as_json:
        click.echo(json.dumps({k: getattr(line, k) for k in ("text", "imports", "exports", "alarms", "last_event")}))
    else:
        click.echo(line.text)


def alarm_rows(conn: psycopg.Connection[Any], show_all: bool = False) -> list[dict[str, Any]]:
    """The pending alarms (or the whole history), oldest first, times as text."""
    cur = conn.execute(
        "select alarm_no, alarm_id, known, machine_id, alarm_text, raised_by, raised_at, cleared_by, cleared_at "
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


def clear_alarm(bus: BlockingBus, alarm_no: int, by: str) -> Message:
    """ALARM_CLR_REQ to the Cell Alarm Server; returns its Alarm_Clear_Ack."""
    conv, batch = bus.request(
        "ALARM_CLR_REQ", message("Alarm_Clear_Request", alarm_no=alarm_no, cleared_by=by), to="cas", timeout=TIMEOUT
    )
    conv.end()
    return batch.first


def read_status_line(bus: BlockingBus) -> Message:
    """STATUS_LN to the Status Line Server; returns its Status_Line."""
    conv, batch = bus.request("STATUS_LN", message("Status_Line_Get"), to="sls", timeout=TIMEOUT)
    conv.end()
    return batch.first


commands = [alarm_group, status_line]
