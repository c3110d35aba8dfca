"""Quality: `gwc spc` (control charts, the rules broken, Cp and Cpk) and `gwc tool change` (the operator
confirms a tool change: TOOL_CHANGE cleared, the feedback's offsets and the mill's wear start again
from zero, the machine started). docs/quality.md.
"""

from __future__ import annotations

import json
from typing import Any

import click

from gwc.client.alarms import clear_alarm
from gwc.client.machines import START_TIMEOUT, start_machine
from gwc.client.session import hi_bus, hi_conn, rows_of
from gwc.hi import context, json_option
from gwc.quality import store
from gwc.quality.charts import charts


def _reader(conn: Any) -> store.Reader:
    def read(sql: str, params: Any = ()) -> list[tuple[Any, ...]]:
        rows = conn.execute(sql, tuple(params)).fetchall()
        conn.rollback()
        return list(rows)

    return read


def _num(v: float | None, fmt: str = ".3f") -> str:
    return "-" if v is None else format(v, fmt)


@click.command("spc")
@click.option("--machine", help="Only this machine's charts (the machine that made the parts).")
@click.option("--feature", help="Only this feature's charts.")
@json_option
def spc_command(machine: str | None, feature: str | None, as_json: bool) -> None:
    """Control charts of the measured features (individuals), the Western Electric rules broken, Cp, Cpk."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        found = charts(_reader(conn), cfg, machine, feature)
    if as_json:
        click.echo(json.dumps(found, default=str, indent=1))
        return
    if not found:
        click.echo("(no measured features)")
        return
    for c in found:
        click.echo(
            f"{c['machine_id']} {c['recipe_id']} {c['feature']}: {c['points']} parts, nominal {c['nominal']:g} "
            f"+/- {c['tol']:g}, CL {_num(c['center'], '.4f')} UCL {_num(c['ucl'], '.4f')} LCL {_num(c['lcl'], '.4f')}, "
            f"Cp {_num(c['cp'], '.2f')} Cpk {_num(c['cpk'], '.2f')}, {c['out_of_tolerance']} out of tolerance"
        )
        for line in c["drawing"]:
            click.echo(f"  {line}")
        for v in c["violations"][:10]:
            click.echo(f"  part {v['part']} (run {v['run']}): {v['text']}")
        if len(c["violations"]) > 10:
            click.echo(f"  ... {len(c['violations']) - 10} more")


@click.group("tool")
def tool_group() -> None:
    """A machine's tool (quality: feedback and wear)."""


@tool_group.command("change")
@click.argument("machine_id")
@click.option("--by", default=None, help="Who changed it (default: user@hi.pid).")
@click.option("--note", default=None)
@click.option("--no-start", is_flag=True, help="Do not start the machine afterwards.")
def tool_change(machine_id: str, by: str | None, note: str | None, no_start: bool) -> None:
    """Confirm the tool of MACHINE_ID was changed: recorded, its TOOL_CHANGE alarms cleared, the
    feedback's offsets and the wear start again from zero, and the machine started again."""
    cfg, log = context()
    cfg.machine(machine_id)
    with hi_conn(cfg, log) as conn:
        conn.execute(
            "INSERT INTO tool_changes (machine_id, confirmed_by, note) VALUES (%s, %s, %s)", (machine_id, by, note)
        )
        conn.commit()
        pending = rows_of(
            conn,
            "SELECT alarm_no FROM alarms WHERE machine_id = %s AND alarm_id = 'TOOL_CHANGE' AND cleared_at IS NULL",
            machine_id,
        )
    click.echo(f"{machine_id}: tool change recorded")
    with hi_bus(cfg, log) as bus:
        for r in pending:
            clear_alarm(bus, int(r["alarm_no"]), by)
            click.echo(f"alarm {r['alarm_no']} (TOOL_CHANGE) cleared")
        if not no_start:
            start_machine(cfg, bus, machine_id, click.echo, START_TIMEOUT)


commands = [spc_command, tool_group]
