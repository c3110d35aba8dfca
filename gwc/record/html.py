"""`gwc report html`: one self-contained page (inline SVG and CSS, no script, nothing fetched) with a
state timeline per machine, OEE per machine and a downtime Pareto, above the tables they are drawn from.

Each machine's timeline is `<svg class="timeline" id="timeline-<machine>">`, one `<rect>` per segment
carrying its E10 state (data-e10), so a test (or a person's browser tools) finds every machine there.
"""

from __future__ import annotations

from datetime import datetime
from html import escape
from typing import Any

import psycopg

from gwc.config import RecordConfig
from gwc.quality import spc
from gwc.quality import store as quality_store
from gwc.record import store

COLOURS = {
    "productive": "#2e9d4a",
    "standby": "#f2c94c",
    "engineering": "#9b59b6",
    "scheduled_downtime": "#2f80ed",
    "unscheduled_downtime": "#d64545",
    "non_scheduled": "#9aa3ad",
}
WIDTH = 900  # px of a timeline's time axis
CSS = """
body { font: 14px/1.4 system-ui, sans-serif; margin: 24px; color: #1d2530; background: #fff; }
h1 { font-size: 22px; margin: 0 0 4px; } h2 { font-size: 17px; margin: 28px 0 8px; }
.sub { color: #5b6672; margin-bottom: 16px; }
.machine { margin: 6px 0; } .machine .name { display: inline-block; width: 110px; font-weight: 600; }
svg.timeline { vertical-align: middle; border: 1px solid #cfd6dd; background: #f5f7f9; }
.legend span { display: inline-block; margin-right: 14px; } .legend i { display: inline-block; width: 12px;
 height: 12px; margin-right: 4px; vertical-align: -1px; }
table { border-collapse: collapse; margin: 6px 0 16px; } th, td { border: 1px solid #cfd6dd; padding: 3px 8px;
 text-align: right; } th { background: #eef1f4; } td.l, th.l { text-align: left; }
.charts { display: flex; gap: 36px; flex-wrap: wrap; }
"""


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def _timeline_svg(machine_id: str, segs: list[store.Segment], since: datetime, until: datetime) -> str:
    span = (until - since).total_seconds() or 1.0
    rects = []
    merged: list[store.Segment] = []
    for s in segs:  # one rect per run of the same state, and none narrower than a tenth of a pixel
        if merged and merged[-1].e10 == s.e10 and merged[-1].end == s.start:
            merged[-1] = store.Segment(merged[-1].start, s.end, merged[-1].status, merged[-1].cause, s.e10)
        elif s.seconds / span * WIDTH >= 0.1 or not merged:
            merged.append(s)
        else:
            merged[-1] = store.Segment(merged[-1].start, s.end, merged[-1].status, merged[-1].cause, merged[-1].e10)
    for s in merged:
        x = (s.start - since).total_seconds() / span * WIDTH
        w = max(0.5, s.seconds / span * WIDTH)
        tip = f"{s.status} ({s.e10}, {s.cause}) {s.start:%H:%M:%S}-{s.end:%H:%M:%S} {s.seconds:.0f}s"
        rects.append(
            f'<rect x="{x:.2f}" y="0" width="{w:.2f}" height="22" fill="{COLOURS[s.e10]}" '
            f'data-e10="{s.e10}" data-status="{escape(s.status)}"><title>{escape(tip)}</title></rect>'
        )
    mid = escape(machine_id)
    return (
        f'<div class="machine"><span class="name">{mid}</span>'
        f'<svg class="timeline" id="timeline-{mid}" data-machine="{mid}" width="{WIDTH}" height="22" '
        f'viewBox="0 0 {WIDTH} 22" xmlns="http://www.w3.org/2000/svg">{"".join(rects)}</svg></div>'
    )


def _oee_svg(machines: list[dict[str, Any]]) -> str:
    bar_h, gap, label_w, w = 18, 8, 110, 300
    rows = []
    for i, m in enumerate(machines):
        y = i * (bar_h + gap)
        v = m["oee"] or 0.0
        rows.append(
            f'<text x="0" y="{y + 13}" font-size="12">{escape(m["machine_id"])}</text>'
            f'<rect x="{label_w}" y="{y}" width="{w}" height="{bar_h}" fill="#eef1f4"/>'
            f'<rect class="oee-bar" data-machine="{escape(m["machine_id"])}" x="{label_w}" y="{y}" '
            f'width="{min(1.0, v) * w:.1f}" height="{bar_h}" fill="#2e9d4a"/>'
            f'<text x="{label_w + w + 6}" y="{y + 13}" font-size="12">OEE {_pct(m["oee"])}</text>'
        )
    h = max(1, len(machines)) * (bar_h + gap)
    return (
        f'<svg id="oee" width="{label_w + w + 90}" height="{h}" xmlns="http://www.w3.org/2000/svg">'
        f"{''.join(rows)}</svg>"
    )


def _pareto_svg(downtime: list[dict[str, Any]]) -> str:
    if not downtime:
        return '<svg id="pareto" width="360" height="40"><text x="0" y="20">no downtime</text></svg>'
    w, h, pad = 380, 200, 30
    total = sum(d["seconds"] for d in downtime) or 1.0
    top = downtime[0]["seconds"] or 1.0
    bw = (w - pad) / len(downtime)
    parts, cum, points = [], 0.0, []
    for i, d in enumerate(downtime):
        bh = d["seconds"] / top * (h - pad - 10)
        x = pad + i * bw
        label = escape(d["reason"] or "(none)")
        parts.append(
            f'<rect class="pareto-bar" x="{x + 4:.1f}" y="{h - pad - bh:.1f}" width="{bw - 8:.1f}" height="{bh:.1f}" '
            f'fill="#d64545"><title>{label}: {d["seconds"]:.0f}s, {d["events"]} event(s)</title></rect>'
            f'<text x="{x + bw / 2:.1f}" y="{h - pad + 14}" font-size="11" text-anchor="middle">{label}</text>'
        )
        cum += d["seconds"]
        points.append(f"{x + bw / 2:.1f},{(h - pad) - cum / total * (h - pad - 10):.1f}")
    line = f'<polyline points="{" ".join(points)}" fill="none" stroke="#1d2530" stroke-width="1.5"/>'
    axis = f'<line x1="{pad}" y1="{h - pad}" x2="{w}" y2="{h - pad}" stroke="#5b6672"/>'
    return f'<svg id="pareto" width="{w}" height="{h}" xmlns="http://www.w3.org/2000/svg">{axis}{"".join(parts)}{line}</svg>'


def _table(rows: list[dict[str, Any]], cols: list[str], left: tuple[str, ...] = ()) -> str:
    head = "".join(f'<th class="{"l" if c in left else ""}">{escape(c)}</th>' for c in cols)
    body = "".join(
        "<tr>"
        + "".join(
            f'<td class="{"l" if c in left else ""}">{escape("" if r.get(c) is None else str(r.get(c)))}</td>'
            for c in cols
        )
        + "</tr>"
        for r in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _spc_svg(c: spc.Chart, title: str, lsl: float, usl: float) -> str:
    """One control chart (docs/quality.md): the points, the centre line and 3-sigma limits, the tolerance,
    a point that broke a rule in red."""
    w, h, pad = 640, 160, 8
    values = c.values
    if c.limits is None or not values:
        return f"<p>{escape(title)}: too few points for limits</p>"
    lim = c.limits
    lo, hi = min(min(values), lim.lcl, lsl), max(max(values), lim.ucl, usl)
    span = (hi - lo) or 1.0

    def y(v: float) -> float:
        return pad + (hi - v) / span * (h - 2 * pad)

    def x(i: int) -> float:
        return pad + i * (w - 2 * pad) / max(1, len(values) - 1)

    lines = "".join(
        f'<line x1="{pad}" x2="{w - pad}" y1="{y(v):.1f}" y2="{y(v):.1f}" stroke="{colour}" stroke-dasharray="{dash}">'
        f"<title>{name} {v:.4f}</title></line>"
        for name, v, colour, dash in (
            ("UCL", lim.ucl, "#c33", "4 3"),
            ("CL", lim.center, "#393", ""),
            ("LCL", lim.lcl, "#c33", "4 3"),
            ("USL", usl, "#999", "1 3"),
            ("LSL", lsl, "#999", "1 3"),
        )
    )
    path = " ".join(f"{x(i):.1f},{y(v):.1f}" for i, v in enumerate(values))
    bad = {v.index: v.text for v in c.violations}
    dots = "".join(
        f'<circle cx="{x(i):.1f}" cy="{y(v):.1f}" r="{3 if i in bad else 2}" fill="{"#d00" if i in bad else "#333"}">'
        f"<title>part {i + 1}: {v:.4f}{escape(' - ' + bad[i]) if i in bad else ''}</title></circle>"
        for i, v in enumerate(values)
    )
    cpk = "-" if c.cpk is None else f"{c.cpk:.2f}"
    return (
        f"<h3>{escape(title)} &middot; Cpk {cpk} &middot; {len(c.violations)} rule(s) broken</h3>"
        f'<svg width="{w}" height="{h}" role="img">{lines}<polyline points="{path}" fill="none" stroke="#333" '
        f'stroke-width="1"/>{dots}</svg>'
    )


def spc_section(conn: psycopg.Connection[Any], settings: tuple[tuple[str, ...], int, int], ids: list[str]) -> str:
    """The control charts of the machines' measured features, or nothing where none were measured."""
    rules, baseline, window = settings

    def read(sql: str, params: Any = ()) -> list[tuple[Any, ...]]:
        return list(conn.execute(sql, tuple(params)).fetchall())

    points = [p for p in quality_store.points(read, limit=window) if p.machine_id in ids]
    charts = []
    for key in sorted({(p.machine_id, p.recipe_id, p.feature) for p in points}):
        series = [p for p in points if (p.machine_id, p.recipe_id, p.feature) == key]
        lsl, usl = series[-1].nominal - series[-1].tol, series[-1].nominal + series[-1].tol
        c = spc.chart(key[2], [p.value for p in series], lsl, usl, rules, baseline)
        charts.append(_spc_svg(c, f"{key[0]} {key[1]} {key[2]}", lsl, usl))
    return "<h2>Control charts (SPC)</h2>" + "".join(charts) if charts else ""


def render(
    conn: psycopg.Connection[Any],
    rec: RecordConfig,
    cell_name: str,
    since: datetime,
    until: datetime,
    machines: list[str] | None = None,
    spc_settings: tuple[tuple[str, ...], int, int] | None = None,
) -> str:
    """The page, as text (with `spc_settings`, the control charts of measured features: docs/quality.md)."""
    rep = store.oee(conn, rec, since, until, machines)
    ids = [m["machine_id"] for m in rep["machines"]]
    timelines = "".join(_timeline_svg(mid, store.timeline(conn, rec, mid, since, until), since, until) for mid in ids)
    events = [e.as_json() for e in store.downtime_events(conn, since=since, until=until) if e.machine_id in ids]
    legend = "".join(f'<span><i style="background:{c}"></i>{s.replace("_", " ")}</span>' for s, c in COLOURS.items())
    oee_rows = [
        {**m, **{k: _pct(m[k]) for k in ("availability", "performance", "quality", "oee")}}
        for m in [*rep["machines"], {"machine_id": "(cell)", **rep["cell"]}]
    ]
    cols = ["machine_id", "planned_s", "run_s", "down_s", "availability", "performance", "quality", "oee", "parts"]
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{escape(cell_name)}: production record</title>
<style>{CSS}</style></head><body>
<h1>{escape(cell_name)}: production record</h1>
<div class="sub">{since:%Y-%m-%d %H:%M:%S %Z} to {until:%Y-%m-%d %H:%M:%S %Z} &middot; cell OEE {
        _pct(rep["cell"]["oee"])
    }
 (availability {_pct(rep["cell"]["availability"])}, performance {_pct(rep["cell"]["performance"])},
 quality {_pct(rep["cell"]["quality"])})</div>
<h2>Machine states (SEMI E10)</h2>
<div class="legend">{legend}</div>
<div id="timelines">{timelines}</div>
<div class="charts"><div><h2>OEE per machine</h2>{_oee_svg(rep["machines"])}</div>
<div><h2>Downtime Pareto (cell)</h2>{_pareto_svg(rep["cell"]["downtime"])}</div></div>
<h2>OEE</h2>{_table(oee_rows, cols + ["good_parts"], ("machine_id",))}
<h2>Downtime by reason</h2>{
        _table(
            [{**d, "reason": d["reason"] or "(none given)"} for d in rep["cell"]["downtime"]],
            ["reason", "seconds", "events"],
            ("reason",),
        )
    }
<h2>Downtime events</h2>{
        _table(
            events,
            ["event_id", "machine_id", "started_at", "ended_at", "cause", "reason", "e10_state"],
            ("machine_id", "started_at", "ended_at", "cause", "reason", "e10_state"),
        )
    }
{spc_section(conn, spc_settings, ids) if spc_settings else ""}
</body></html>
"""
