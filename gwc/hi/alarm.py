"""Alarms and the status line: `gwc alarm list`, `gwc alarm clear`, `gwc status-line`.

The list is read from the alarm history (reads are free); clearing goes through the Cell Alarm
Server (ALARM_CLR_REQ), the table's one writer, which then tells the waiting WC (ALARM_CLEAR). The
status line is asked of the Status Line Server (STATUS_LN), as every HI screen of 7.4 shows it.
The conversations are gwc.client.alarms'.
"""

from __future__ import annotations

import json

import click

from gwc.client.alarms import (
    STATUS_LINE_FIELDS,
    alarm_rows,
    clear_alarm,
    describe_alarm,
    description_rows,
    read_status_line,
)
from gwc.client.session import hi_bus, hi_conn
from gwc.hi import context, json_option, table


@click.group("alarm")
def alarm_group() -> None:
    """The cell's alarms (Cell Alarm Server)."""


@alarm_group.command("list")
@click.option("--all", "show_all", is_flag=True, help="The whole history, not only the pending alarms.")
@json_option
def alarm_list(show_all: bool, as_json: bool) -> None:
    """Pending alarms (oldest first), or the whole history with --all."""
    cfg, log = context()
    columns = ["alarm_no", "alarm_id", "machine_id", "alarm_text", "raised_by", "raised_at"]
    with hi_conn(cfg, log) as conn:
        rows = alarm_rows(conn, show_all)
    table(rows, columns + (["cleared_by", "cleared_at"] if show_all else []) + ["actions_taken"], as_json)


@alarm_group.command("clear")
@click.argument("alarm_no", type=int)
@click.option("--by", default=None, help="Who clears it (default: user@hi.pid).")
def alarm_clear(alarm_no: int, by: str | None) -> None:
    """Clear a pending alarm: the machine waiting on it continues."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        clear_alarm(bus, alarm_no, by)
    click.echo(f"alarm {alarm_no} cleared")


@alarm_group.command("describe")
@click.argument("alarm_id")
@click.option("--text", default=None, help="What the alarm means, for the operator.")
@click.option("--severity", type=click.Choice(["note", "warning", "error"]), default=None)
@click.option(
    "--actions",
    default=None,
    help="What the Cell Alarm Server does when it is raised: shutdown, page, comma-separated; 'none' for nothing.",
)
def alarm_describe(alarm_id: str, text: str | None, severity: str | None, actions: str | None) -> None:
    """Add or change an alarm's description and its actions (1.4.5): `--actions shutdown,page`."""
    cfg, log = context()
    acts = None if actions is None else [a.strip() for a in actions.split(",") if a.strip() not in ("", "none")]
    with hi_bus(cfg, log) as bus:
        now = describe_alarm(bus, alarm_id, text, severity, acts)
    click.echo(f"alarm {alarm_id}: {now}")


@alarm_group.command("descriptions")
@json_option
def alarm_descriptions(as_json: bool) -> None:
    """The alarm description table: every alarm, its severity and what the Cell Alarm Server does for it."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        rows = description_rows(conn)
    table(rows, ["alarm_id", "severity", "actions", "alarm_text"], as_json)


@click.command("status-line")
@json_option
def status_line_command(as_json: bool) -> None:
    """The operator's status line: lots waiting for import or export, pending alarms, the last event."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        line = read_status_line(bus)
    if as_json:
        click.echo(json.dumps({k: getattr(line, k) for k in STATUS_LINE_FIELDS}))
    else:
        click.echo(line.text)


commands = [alarm_group, status_line_command]
