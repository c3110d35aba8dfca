"""What the web's record and quality pages show (docs/web.md): OEE, the machines' state timelines and
downtime over a window, the control charts, the recipe library, and the genealogy searches. Each is
the production record's or the quality work's own read (gwc.record.store, gwc.quality.charts,
gwc.client.recipes), put in the shape the pages draw: the web holds no SQL of its own for them.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

import psycopg

from gwc.client.record import parse_when
from gwc.config import Config
from gwc.errors import GwcError
from gwc.record import store

WINDOW = timedelta(hours=8)  # the live pages' window: the last this long
TIMELINE_MAX = 400  # segments of a machine's timeline sent to a page (the narrowest merged away)


def window(cfg: Config, since: str | None, until: str | None) -> tuple[datetime, datetime]:
    """The window a page asks for (`since`, `until` as `gwc report` takes them), else the last WINDOW."""
    now = datetime.now(UTC)
    tz = cfg.record.timezone
    a = parse_when(since, tz, now) if since else now - WINDOW
    b = parse_when(until, tz, now) if until else now
    if b <= a:
        raise GwcError(f"until ({b.isoformat()}) must be after since ({a.isoformat()})")
    return a, b


def _segments(segs: list[store.Segment], since: datetime, until: datetime) -> list[dict[str, Any]]:
    """A timeline's segments as the page draws them: neighbours of one E10 state merged, and past
    TIMELINE_MAX the narrowest folded into the one before (a page is a few hundred pixels wide); the
    last, the machine's state now, is always kept."""
    span = (until - since).total_seconds() or 1.0
    out: list[dict[str, Any]] = []
    for s in segs:
        if out and out[-1]["e10"] == s.e10:
            out[-1]["end"] = s.end.isoformat()
            out[-1]["seconds"] = round(out[-1]["seconds"] + s.seconds, 3)
            continue
        out.append(
            {
                "start": s.start.isoformat(),
                "end": s.end.isoformat(),
                "seconds": round(s.seconds, 3),
                "status": s.status,
                "cause": s.cause,
                "e10": s.e10,
                "recipe_id": s.recipe_id,
            }
        )
    if len(out) <= TIMELINE_MAX:
        return out
    folded = out[:1]
    for seg in out[1:-1]:
        if seg["seconds"] / span < 1 / (4 * TIMELINE_MAX):
            folded[-1]["end"] = seg["end"]
            folded[-1]["seconds"] = round(folded[-1]["seconds"] + seg["seconds"], 3)
        else:
            folded.append(seg)
    return [*folded, out[-1]]


def record_view(cfg: Config, conn: psycopg.Connection[Any], since: datetime, until: datetime) -> dict[str, Any]:
    """The OEE, timeline and downtime pages' data over [since, until): `gwc report oee --json`, each
    machine's timeline, the downtime events (those still open too), and the reason tree."""
    try:
        ids = [m.id for m in cfg.machines] or None
        rep = store.oee(conn, cfg.record, since, until, ids)
        timelines = {
            m["machine_id"]: _segments(store.timeline(conn, cfg.record, m["machine_id"], since, until), since, until)
            for m in rep["machines"]
        }
        events = [e.as_json() for e in store.downtime_events(conn, since=since, until=until)]
    finally:
        conn.rollback()  # reads only: no transaction left open on the web's connection
    return {
        "since": since.isoformat(),
        "until": until.isoformat(),
        "oee": rep,
        "timelines": timelines,
        "downtime": events,
        "reasons": cfg.record.tree(),
    }


def spc_view(cfg: Config, conn: psycopg.Connection[Any], machine: str | None = None) -> list[dict[str, Any]]:
    """The control charts `gwc spc --json` shows (one per machine, recipe and feature measured)."""
    from gwc.quality.charts import charts

    def read(sql: str, params: Any = ()) -> list[tuple[Any, ...]]:
        rows = conn.execute(sql, tuple(params)).fetchall()
        conn.rollback()
        return list(rows)

    out = charts(read, cfg, machine, None)
    for c in out:
        c.pop("drawing", None)  # the console's picture; the page draws its own
    return out


def trace_view(conn: psycopg.Connection[Any], entity_id: int) -> dict[str, Any]:
    """`gwc trace entity E`: the entity's lot, work order, runs, operator actions and states."""
    try:
        tr = store.trace_entity(conn, entity_id)
        if tr is None:
            raise GwcError(f"unknown lot entity {entity_id}")
        for step in tr["steps"]:
            step.pop("_checksum", None)
        tr["states"] = store.entity_states(conn, entity_id)
    finally:
        conn.rollback()
    return tr


def where_view(
    cfg: Config,
    conn: psycopg.Connection[Any],
    machine: str | None,
    recipe: str | None,
    since: str | None,
    until: str | None,
) -> list[dict[str, Any]]:
    """`gwc trace where`: every entity that ran on a machine, with a recipe (RECIPE or RECIPE@VERSION),
    in a window: the reverse query a recall needs."""
    version = None
    if recipe and "@" in recipe:
        recipe, _, v = recipe.partition("@")
        if not v.isdigit():
            raise GwcError(f"recipe {recipe}@{v}: the version must be a whole number")
        version = int(v)
    tz = cfg.record.timezone
    a = parse_when(since, tz) if since else None
    b = parse_when(until, tz) if until else None
    try:
        return store.trace_where(conn, machine or None, recipe or None, version, a, b)
    finally:
        conn.rollback()
