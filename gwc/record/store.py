"""The production record, read: state timelines, downtime events, OEE, genealogy (docs/record.md).

Reads only (anyone may read every table): the Machine Server writes machine_state_history and
downtime_events, the Lot Server entity_state_history and operator_actions, the WCs the runs. Each
function takes an open connection and returns dataclasses or the JSON-ready dicts the issue's
shapes promise (`gwc report oee --json`, `gwc trace ...`, `gwc downtime list --json`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from itertools import pairwise
from typing import Any

import psycopg

from gwc.config import RecordConfig
from gwc.record.calendar import Interval, overlap, planned_intervals

RUNNING = ("Running", "Run_Shut")
BAD_RESULTS = ("FAIL", "REJECT", "SCRAP")  # a result value that makes a part not good


@dataclass
class Segment:
    """One interval of a machine's timeline, with its SEMI E10 state."""

    start: datetime
    end: datetime
    status: str
    cause: str
    e10: str
    recipe_id: str | None = None
    machine_run_id: int | None = None

    @property
    def seconds(self) -> float:
        return (self.end - self.start).total_seconds()


@dataclass
class DowntimeEvent:
    event_id: int
    machine_id: str
    started_at: datetime
    ended_at: datetime | None
    cause: str
    reason: str | None
    e10_state: str
    note: str | None = None

    def as_json(self) -> dict[str, Any]:
        return {
            "event_id": self.event_id,
            "machine_id": self.machine_id,
            "started_at": _iso(self.started_at),
            "ended_at": _iso(self.ended_at),
            "cause": self.cause,
            "reason": self.reason,
            "e10_state": self.e10_state,
        }


@dataclass
class Run:
    machine_id: str
    machine_run_id: int
    recipe_id: str | None
    entity_id: int | None
    started_at: datetime | None
    ended_at: datetime
    ack_code: str
    results: dict[str, str] = field(default_factory=dict)
    remade: bool = False  # scrapped, or made again after it measured out of tolerance

    @property
    def good(self) -> bool:
        return self.ack_code == "ACK_OK" and not self.remade and not _bad_results(self.results)


def _iso(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat()


def _bad_results(results: dict[str, str]) -> bool:
    return any(str(v).strip().upper() in BAD_RESULTS for v in results.values())


def verdict(ack_code: str | None, results: dict[str, str]) -> str | None:
    """pass, fail, or None (the run has not ended)."""
    if ack_code is None:
        return None
    return "pass" if ack_code == "ACK_OK" and not _bad_results(results) else "fail"


# ----------------------------------------------------------------------------- reads


def machine_ids(conn: psycopg.Connection[Any]) -> list[str]:
    return [r[0] for r in conn.execute("select machine_id from me_config order by machine_id").fetchall()]


def downtime_events(
    conn: psycopg.Connection[Any],
    machine_id: str | None = None,
    open_only: bool = False,
    since: datetime | None = None,
    until: datetime | None = None,
) -> list[DowntimeEvent]:
    """Downtime events, oldest first: of one machine or all, only the open ones, or those overlapping
    [since, until)."""
    rows = conn.execute(
        "select event_id, machine_id, started_at, ended_at, cause, reason, e10_state, note from downtime_events "
        "where (%(m)s::text is null or machine_id = %(m)s) and (not %(open)s or ended_at is null) "
        "and (%(until)s::timestamptz is null or started_at < %(until)s) "
        "and (%(since)s::timestamptz is null or coalesce(ended_at, 'infinity') > %(since)s) "
        "order by started_at, event_id",
        {"m": machine_id, "open": open_only, "since": since, "until": until},
    ).fetchall()
    return [DowntimeEvent(*r) for r in rows]


def _history(
    conn: psycopg.Connection[Any], machine_id: str, since: datetime, until: datetime
) -> list[tuple[datetime, str, str, str | None, int | None]]:
    """(at, status, cause, recipe_id, machine_run_id) of the machine's changes in [since, until), led by
    the last one before `since` (the state the window begins in)."""
    return conn.execute(
        "(select at, status, cause, recipe_id, machine_run_id from machine_state_history "
        " where machine_id = %(m)s and at < %(since)s order by at desc, id desc limit 1) "
        "union all (select at, status, cause, recipe_id, machine_run_id from machine_state_history "
        " where machine_id = %(m)s and at >= %(since)s and at < %(until)s order by at, id) order by 1",
        {"m": machine_id, "since": since, "until": until},
    ).fetchall()


def timeline(
    conn: psycopg.Connection[Any],
    rec: RecordConfig,
    machine_id: str,
    since: datetime,
    until: datetime,
    events: list[DowntimeEvent] | None = None,
) -> list[Segment]:
    """The machine's states over [since, until) as segments, each with its E10 state; time before the
    first record is left out (unknown). Segments are split where planned time begins or ends."""
    rows = _history(conn, machine_id, since, until)
    planned = planned_intervals(rec.calendar_of(machine_id), since, until, rec.timezone)
    if events is None:
        events = downtime_events(conn, machine_id, since=since, until=until)
    raw: list[Segment] = []
    for i, (at, status, cause, recipe, run) in enumerate(rows):
        start = max(at, since)
        end = rows[i + 1][0] if i + 1 < len(rows) else until
        if end <= start:
            continue
        raw.append(Segment(start, min(end, until), status, cause, "", recipe, run))
    out: list[Segment] = []
    for seg in raw:
        for part, is_planned in _split(seg.start, seg.end, planned):
            s = Segment(part[0], part[1], seg.status, seg.cause, "", seg.recipe_id, seg.machine_run_id)
            s.e10 = _e10(s, is_planned, events)
            out.append(s)
    return out


def _split(start: datetime, end: datetime, planned: list[Interval]) -> list[tuple[Interval, bool]]:
    """[start, end) cut at the edges of planned time: (part, planned?) in order."""
    cuts = sorted({start, end, *(t for p in planned for t in p if start < t < end)})
    out = []
    for a, b in pairwise(cuts):
        mid = a + (b - a) / 2
        out.append(((a, b), any(p[0] <= mid < p[1] for p in planned)))
    return out


def _e10(seg: Segment, is_planned: bool, events: list[DowntimeEvent]) -> str:
    """SEMI E10's basic state of a segment (docs/record.md, States)."""
    if seg.status in RUNNING:
        return "productive"
    if not is_planned:
        return "non_scheduled"
    if seg.status == "Idle":
        return "standby"
    if seg.status in ("Setup", "Setup_Shut"):
        return "scheduled_downtime"  # E10 counts a setup as scheduled downtime
    for ev in events:  # Shutdown: the stop's own state
        if ev.started_at <= seg.start + (seg.end - seg.start) / 2 and (ev.ended_at is None or ev.ended_at > seg.start):
            return "unscheduled_downtime" if ev.e10_state == "non_scheduled" else ev.e10_state
    return "unscheduled_downtime"


def runs(conn: psycopg.Connection[Any], machine_id: str | None, since: datetime, until: datetime) -> list[Run]:
    """The runs that ended in [since, until) (MACHINE_RUN_OUTCOME), with their recipe, entity and start
    from the history, their results, and whether the entity made that recipe again later."""
    rows = conn.execute(
        "select o.machine_id, o.machine_run_id, h.recipe_id, h.entity_id, h.at, o.ended_at, o.ack_code, "
        "  coalesce((select jsonb_object_agg(r.param, r.value) from machine_run_result r "
        "            where r.machine_run_id = o.machine_run_id and r.machine_id = o.machine_id), '{}'::jsonb), "
        # not good though the run went well: the entity was scrapped (or failed), or the part was
        # re-made: the entity ran this recipe again after its next run (the measuring) found it bad
        "  h.entity_id is not null and (exists (select 1 from lot_status s where s.entity_id = h.entity_id "
        "      and (s.state = 'failed' or s.reason like 'SCRAP%%')) "
        "    or (exists (select 1 from machine_state_history l where l.entity_id = h.entity_id "
        "          and l.recipe_id = h.recipe_id and l.status = 'Running' and l.at > h.at) "
        "        and exists (select 1 from machine_run_outcome o2 left join machine_run_result r2 "
        "          on r2.machine_run_id = o2.machine_run_id and r2.machine_id = o2.machine_id "
        "          where o2.machine_run_id = nx.machine_run_id and o2.machine_id = nx.machine_id "
        "          and (o2.ack_code <> 'ACK_OK' or upper(r2.value) = any(%(bad)s))))) "
        "from machine_run_outcome o "
        "left join lateral (select recipe_id, entity_id, at from machine_state_history x "
        "   where x.machine_id = o.machine_id and x.machine_run_id = o.machine_run_id and x.status = 'Running' "
        "   order by at limit 1) h on true "
        "left join lateral (select n.machine_id, n.machine_run_id from machine_state_history n "
        "   where n.entity_id = h.entity_id and n.status = 'Running' and n.at > h.at order by n.at limit 1) nx on true "
        "where (%(m)s::text is null or o.machine_id = %(m)s) and o.ended_at >= %(since)s and o.ended_at < %(until)s "
        "order by o.ended_at",
        {"m": machine_id, "since": since, "until": until, "bad": list(BAD_RESULTS)},
    ).fetchall()
    return [
        Run(r[0], r[1], r[2], r[3], r[4], r[5], r[6], {str(k): str(v) for k, v in (r[7] or {}).items()}, bool(r[8]))
        for r in rows
    ]


# ----------------------------------------------------------------------------- OEE


def _ratio(a: float, b: float) -> float | None:
    return None if b <= 0 else a / b


def _figures(
    planned: float,
    run: float,
    down: float,
    ideal: float,
    parts: int,
    good: int,
    downtime: dict[str | None, list[float]],
) -> dict[str, Any]:
    planned, run, down = round(planned, 3), round(run, 3), round(down, 3)  # the ratios are those of the figures shown
    availability = _ratio(run, planned)
    performance = _ratio(ideal, run)
    quality = _ratio(good, parts)
    oee = None if None in (availability, performance, quality) else availability * performance * quality  # type: ignore[operator]
    pareto = sorted(downtime.items(), key=lambda kv: (-kv[1][0], str(kv[0])))
    return {
        "planned_s": planned,
        "run_s": run,
        "down_s": down,
        "availability": availability,
        "performance": performance,
        "quality": quality,
        "oee": oee,
        "parts": parts,
        "good_parts": good,
        "downtime": [{"reason": r, "seconds": round(v[0], 3), "events": int(v[1])} for r, v in pareto],
    }


def oee(
    conn: psycopg.Connection[Any],
    rec: RecordConfig,
    since: datetime,
    until: datetime,
    machines: list[str] | None = None,
) -> dict[str, Any]:
    """`gwc report oee --json`: each machine's and the cell's figures over [since, until) (docs/record.md).

    availability = run time / planned time; performance = sum of the runs' ideal cycle times / run time
    (a recipe without record.ideal_cycle_s: its fastest run on that machine in the window); quality =
    good parts / parts. Run and down time count only inside planned time; time before a machine's first
    record (a cell just installed, history pruned) is unknown and counts as nothing."""
    ids = machines if machines else machine_ids(conn)
    out = []
    cell = {"planned": 0.0, "run": 0.0, "down": 0.0, "ideal": 0.0, "parts": 0, "good": 0}
    cell_down: dict[str | None, list[float]] = {}
    all_runs = runs(conn, None, since, until)
    for mid in ids:
        # time before the machine's first record is unknown: not planned, not counted
        first = conn.execute("select min(at) from machine_state_history where machine_id = %s", (mid,)).fetchone()
        known = max(since, first[0]) if first and first[0] is not None else until
        planned = planned_intervals(rec.calendar_of(mid), known, until, rec.timezone)
        planned_s = sum((b - a).total_seconds() for a, b in planned)
        events = downtime_events(conn, mid, since=since, until=until)
        segs = timeline(conn, rec, mid, since, until, events)
        run_s = sum(overlap((s.start, s.end), planned) for s in segs if s.status in RUNNING)
        per_reason: dict[str | None, list[float]] = {}
        down_s = 0.0
        for ev in events:
            secs = overlap((max(ev.started_at, since), min(ev.ended_at or until, until)), planned)
            down_s += secs
            entry = per_reason.setdefault(ev.reason, [0.0, 0])
            entry[0] += secs
            entry[1] += 1
            c = cell_down.setdefault(ev.reason, [0.0, 0])
            c[0] += secs
            c[1] += 1
        mine = [r for r in all_runs if r.machine_id == mid]
        ideal = _ideal_total(rec, mine, segs)
        good = sum(1 for r in mine if r.good)
        fig = _figures(planned_s, run_s, down_s, ideal, len(mine), good, per_reason)
        out.append({"machine_id": mid, **fig})
        for k, v in (("planned", planned_s), ("run", run_s), ("down", down_s), ("ideal", ideal)):
            cell[k] += v
        cell["parts"] += len(mine)
        cell["good"] += good
    return {
        "since": since.isoformat(),
        "until": until.isoformat(),
        "machines": out,
        "cell": _figures(
            cell["planned"],
            cell["run"],
            cell["down"],
            cell["ideal"],
            int(cell["parts"]),
            int(cell["good"]),
            cell_down,
        ),
    }


def _ideal_total(rec: RecordConfig, mine: list[Run], segs: list[Segment]) -> float:
    """Sum of the ideal cycle times of these runs: configured per recipe, else the recipe's fastest
    run seen in the window (so performance never credits a run faster than the best one)."""
    fastest: dict[str | None, float] = {}
    for s in segs:
        if s.status == "Running" and s.seconds > 0:
            fastest[s.recipe_id] = min(fastest.get(s.recipe_id, s.seconds), s.seconds)
    total = 0.0
    for r in mine:
        if r.recipe_id in rec.ideal_cycle_s:
            total += rec.ideal_cycle_s[r.recipe_id]
        elif r.recipe_id in fastest:
            total += fastest[r.recipe_id]
        elif r.started_at is not None:
            total += max(0.0, (r.ended_at - r.started_at).total_seconds())
    return total


# ----------------------------------------------------------------------------- genealogy


def trace_entity(conn: psycopg.Connection[Any], entity_id: int) -> dict[str, Any] | None:
    """`gwc trace entity E --json`: its lot and work order, its runs in order, the operator's actions."""
    head = conn.execute(
        "select e.entity_id, e.lot_id, l.work_order_id, s.state from lot_entities e join lots l using (lot_id) "
        "left join lot_status s on s.entity_id = e.entity_id where e.entity_id = %s",
        (entity_id,),
    ).fetchone()
    if head is None:
        return None
    steps = conn.execute(
        "select h.machine_id, h.recipe_id, h.recipe_version, h.recipe_checksum, h.machine_run_id, h.at, o.ended_at, "
        "  o.ack_code, coalesce((select jsonb_object_agg(r.param, r.value) from machine_run_result r "
        "            where r.machine_run_id = h.machine_run_id and r.machine_id = h.machine_id), '{}'::jsonb), "
        # quality (docs/quality.md): each feature measured or offset given, as numbers
        "  coalesce((select jsonb_agg(jsonb_build_object('feature', f.feature, 'measured', f.measured, "
        "    'nominal', f.nominal, 'tol', f.tol, 'offset', f.offset_used, 'workpiece', f.workpiece, "
        "    'in_tol', f.in_tol) order by f.feature) from run_features f "
        "    where f.machine_run_id = h.machine_run_id and f.machine_id = h.machine_id), '[]'::jsonb) "
        "from machine_state_history h left join machine_run_outcome o "
        "  on o.machine_run_id = h.machine_run_id and o.machine_id = h.machine_id "
        "where h.entity_id = %s and h.status = 'Running' order by h.at, h.id",
        (entity_id,),
    ).fetchall()
    actions = conn.execute(
        "select action, by, at from operator_actions where entity_id = %s order by at, id", (entity_id,)
    ).fetchall()
    out_steps = []
    for machine, recipe, version, checksum, run, started, ended, code, results, features in steps:
        res = {str(k): str(v) for k, v in (results or {}).items()}
        out_steps.append(
            {
                "machine_id": machine,
                "recipe_id": recipe,
                "recipe_version": version,
                "machine_run_id": run,
                "started_at": _iso(started),
                "ended_at": _iso(ended),
                "results": res,
                "verdict": verdict(code, res),
                "features": list(features or []),
                "_checksum": checksum,  # for the table (removed from --json)
            }
        )
    return {
        "entity_id": head[0],
        "lot_id": head[1],
        "work_order_id": head[2],
        "state": head[3],
        "steps": out_steps,
        "actions": [{"action": a, "by": b, "at": _iso(t)} for a, b, t in actions],
    }


def entity_states(conn: psycopg.Connection[Any], entity_id: int) -> list[dict[str, Any]]:
    """The entity's states in order (entity_state_history): state, reason, lot, when."""
    rows = conn.execute(
        "select state, reason, lot_id, at from entity_state_history where entity_id = %s order by at, id",
        (entity_id,),
    ).fetchall()
    return [{"state": s, "reason": r, "lot_id": lot, "at": _iso(t)} for s, r, lot, t in rows]


def trace_where(
    conn: psycopg.Connection[Any],
    machine_id: str | None = None,
    recipe_id: str | None = None,
    version: int | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> list[dict[str, Any]]:
    """`gwc trace where ... --json`: every run there (machine, recipe and version, overlapping the window),
    with its entity: the reverse query a recall needs."""
    rows = conn.execute(
        "select h.entity_id, h.machine_id, h.machine_run_id, h.recipe_id, h.recipe_version, h.at, o.ended_at "
        "from machine_state_history h left join machine_run_outcome o "
        "  on o.machine_run_id = h.machine_run_id and o.machine_id = h.machine_id "
        "where h.status = 'Running' and h.entity_id is not null "
        "and (%(m)s::text is null or h.machine_id = %(m)s) and (%(r)s::text is null or h.recipe_id = %(r)s) "
        "and (%(v)s::int is null or h.recipe_version = %(v)s) "
        "and (%(until)s::timestamptz is null or h.at < %(until)s) "
        "and (%(since)s::timestamptz is null or coalesce(o.ended_at, 'infinity') >= %(since)s) "
        "order by h.at, h.id",
        {"m": machine_id, "r": recipe_id, "v": version, "since": since, "until": until},
    ).fetchall()
    keys = ("entity_id", "machine_id", "machine_run_id", "recipe_id", "recipe_version", "started_at", "ended_at")
    return [dict(zip(keys, (*r[:5], _iso(r[5]), _iso(r[6])))) for r in rows]
