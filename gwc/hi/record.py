"""The production record (docs/record.md): `gwc report oee|html`, `gwc trace entity|where`,
`gwc downtime list|reason|reasons`.

Reports and traces read the history tables (reads are free); a downtime's reason is the Machine
Server's to write, so `gwc downtime reason` asks it over the bus (DOWNTIME_RSN).
"""

from __future__ import annotations

import csv
import io
import json
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import click

from gwc.client.record import parse_when, set_downtime_reason
from gwc.client.session import hi_bus, hi_conn, operator
from gwc.errors import GwcError
from gwc.hi import context, json_option, table
from gwc.record import store

since_option = click.option("--since", default="24h", show_default=True, help="Start: now, today, 8h (ago) or ISO.")
until_option = click.option("--until", default="now", show_default=True, help="End: now, today, 8h (ago) or ISO.")


def _window(since: str, until: str, timezone: str) -> tuple[datetime, datetime]:
    now = datetime.now(UTC)
    a, b = parse_when(since, timezone, now), parse_when(until, timezone, now)
    if b <= a:
        raise click.UsageError(f"--until ({b.isoformat()}) must be after --since ({a.isoformat()})")
    return a, b


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


# ----------------------------------------------------------------------------- gwc report


@click.group("report")
def report_group() -> None:
    """The cell's books: OEE per machine and cell, and a page with the pictures."""


@report_group.command("oee")
@click.option("--machine", "machines", multiple=True, help="Only this machine (repeat for several).")
@since_option
@until_option
@json_option
@click.option("--csv", "as_csv", is_flag=True, help="Print CSV (one row per machine, then the cell).")
def report_oee(machines: tuple[str, ...], since: str, until: str, as_json: bool, as_csv: bool) -> None:
    """Availability x performance x quality = OEE, per machine and for the cell, over the window."""
    cfg, log = context()
    for m in machines:
        cfg.machine(m)
    a, b = _window(since, until, cfg.record.timezone)
    with hi_conn(cfg, log) as conn:
        rep = store.oee(conn, cfg.record, a, b, list(machines) or [m.id for m in cfg.machines] or None)
    if as_json:
        click.echo(json.dumps(rep, indent=1))
        return
    rows = [*rep["machines"], {"machine_id": "(cell)", **rep["cell"]}]
    cols = ["machine_id", "planned_s", "run_s", "down_s", "availability", "performance", "quality", "oee"]
    cols += ["parts", "good_parts"]
    if as_csv:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(cols)
        for r in rows:
            w.writerow([r[c] for c in cols])
        click.echo(buf.getvalue().rstrip("\n"))
        return
    click.echo(f"OEE from {rep['since']} to {rep['until']}")
    pretty = [{**r, **{k: _pct(r[k]) for k in ("availability", "performance", "quality", "oee")}} for r in rows]
    table(pretty, cols)
    down = rep["cell"]["downtime"]
    if down:
        click.echo("\nDowntime by reason (cell):")
        table([{**d, "reason": d["reason"] or "(none given)"} for d in down], ["reason", "seconds", "events"])


@report_group.command("html")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The page to write.")
@click.option("--machine", "machines", multiple=True, help="Only this machine (repeat for several).")
@since_option
@until_option
def report_html(out: Path, machines: tuple[str, ...], since: str, until: str) -> None:
    """One self-contained page (no network needed): a state timeline per machine, OEE per machine and a
    downtime Pareto, above the tables."""
    from gwc.quality import spc
    from gwc.record.html import render

    cfg, log = context()
    for m in machines:
        cfg.machine(m)
    a, b = _window(since, until, cfg.record.timezone)
    with hi_conn(cfg, log) as conn:
        page = render(
            conn,
            cfg.record,
            cfg.cell_name,
            a,
            b,
            list(machines) or [m.id for m in cfg.machines] or None,
            spc.settings(cfg),
        )
    try:
        out.write_text(page, encoding="utf-8")
    except OSError as e:
        raise GwcError(f"cannot write {out}: {e}") from None
    click.echo(f"wrote {out} ({len(page)} bytes)")


# ----------------------------------------------------------------------------- gwc trace


@click.group("trace")
def trace_group() -> None:
    """Genealogy: where a part went (entity), and which parts went somewhere (where)."""


@trace_group.command("entity")
@click.argument("entity_id", type=int)
@json_option
def trace_entity(entity_id: int, as_json: bool) -> None:
    """ENTITY_ID's lot and work order, every run in order (machine, recipe, version, results, verdict),
    and every operator action on it."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        tr = store.trace_entity(conn, entity_id)
        states = store.entity_states(conn, entity_id) if tr is not None and not as_json else []
    if tr is None:
        raise GwcError(f"unknown lot entity {entity_id} (see `gwc lots`)")
    checksums = [s.pop("_checksum") for s in tr["steps"]]
    if as_json:
        click.echo(json.dumps(tr, indent=1))
        return
    click.echo(f"entity {tr['entity_id']}  lot {tr['lot_id']}  work order {tr['work_order_id']}  state {tr['state']}")
    rows = [
        {
            **s,
            "recipe": f"{s['recipe_id']}@{s['recipe_version']}",
            "checksum": (c or "")[:12],
            "results": " ".join(f"{k}={v}" for k, v in s["results"].items()),
        }
        for s, c in zip(tr["steps"], checksums)
    ]
    table(rows, ["machine_id", "recipe", "checksum", "machine_run_id", "started_at", "ended_at", "verdict", "results"])
    click.echo("\nOperator actions:")
    table(tr["actions"], ["at", "action", "by"])
    click.echo("\nStates:")
    table(states, ["at", "state", "lot_id", "reason"])


@trace_group.command("where")
@click.option("--machine", help="Runs on this machine.")
@click.option("--recipe", help="Runs of this recipe, or RECIPE@VERSION.")
@click.option("--since", default=None, help="Runs ending after: now, today, 8h (ago) or ISO.")
@click.option("--until", default=None, help="Runs starting before: now, today, 8h (ago) or ISO.")
@json_option
def trace_where(machine: str | None, recipe: str | None, since: str | None, until: str | None, as_json: bool) -> None:
    """Every entity that ran there (the reverse query a recall needs)."""
    cfg, log = context()
    version = None
    if recipe and "@" in recipe:
        recipe, _, v = recipe.partition("@")
        if not v.isdigit():
            raise click.UsageError(f"--recipe {recipe}@{v}: the version must be a whole number")
        version = int(v)
    tz = cfg.record.timezone
    a = parse_when(since, tz) if since else None
    b = parse_when(until, tz) if until else None
    with hi_conn(cfg, log) as conn:
        rows = store.trace_where(conn, machine, recipe, version, a, b)
    table(
        rows,
        ["entity_id", "machine_id", "machine_run_id", "recipe_id", "recipe_version", "started_at", "ended_at"],
        as_json,
    )


# ----------------------------------------------------------------------------- gwc downtime


@click.group("downtime")
def downtime_group() -> None:
    """Downtime events (stops that were not planned) and their reasons."""


@downtime_group.command("list")
@click.option("--machine", help="Only this machine's.")
@click.option("--open", "open_only", is_flag=True, help="Only the events still open (the machine still down).")
@click.option("--since", default=None, help="Events still open after: now, today, 8h (ago) or ISO.")
@json_option
def downtime_list(machine: str | None, open_only: bool, since: str | None, as_json: bool) -> None:
    """Every downtime event, oldest first: machine, start, end, cause, reason, SEMI E10 state."""
    cfg, log = context()
    a = parse_when(since, cfg.record.timezone) if since else None
    with hi_conn(cfg, log) as conn:
        events = store.downtime_events(conn, machine, open_only, since=a)
    rows = [e.as_json() for e in events]
    if not as_json:
        now = datetime.now(UTC)
        for r, e in zip(rows, events):
            r["seconds"] = f"{((e.ended_at or now) - e.started_at) / timedelta(seconds=1):.0f}"
    table(
        rows, ["event_id", "machine_id", "started_at", "ended_at", "seconds", "cause", "reason", "e10_state"], as_json
    )


@downtime_group.command("reason")
@click.argument("event", metavar="EVENT")
@click.argument("reason")
def downtime_reason(event: str, reason: str) -> None:
    """Give downtime EVENT (its number, or a machine id: its open event) REASON, one of the reason tree's
    (`gwc downtime reasons`)."""
    cfg, log = context()
    if reason not in cfg.record.reasons:
        known = "; ".join(f"{c}: {', '.join(rs)}" for c, rs in cfg.record.tree().items())
        raise click.UsageError(f"{reason!r} is not in the reason tree ({known})")
    event_id = int(event) if event.isdigit() else None
    machine_id = None if event_id is not None else cfg.machine(event).id
    with hi_bus(cfg, log) as bus:
        ack = set_downtime_reason(bus, reason, operator(), event_id=event_id, machine_id=machine_id)
    click.echo(f"downtime {ack.event_id}: {reason} ({ack.e10_state})")


@downtime_group.command("reasons")
@json_option
def downtime_reasons(as_json: bool) -> None:
    """The reason tree of cell.toml [record.reasons]: category, its E10 state, its reasons."""
    cfg, _ = context()
    rows: list[dict[str, Any]] = [
        {"category": c, "e10_state": cfg.record.reasons[rs[0]][1], "reasons": rs} for c, rs in cfg.record.tree().items()
    ]
    if as_json:
        table(rows, [], True)
        return
    table([{**r, "reasons": ", ".join(r["reasons"])} for r in rows], ["category", "e10_state", "reasons"])


commands = [report_group, trace_group, downtime_group]
