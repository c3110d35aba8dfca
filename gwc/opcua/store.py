"""What the gateway reads of the tables (as role gwc_opcua; it owns none): one query each for the
machines, their last runs and results, the pending alarms and the lots in the cell."""

from __future__ import annotations

from typing import Any

MACHINES_SQL = """
select s.machine_id, s.status, s.recipe_id, s.machine_run_id, s.start_time, s.end_time, s.note, s.updated_at,
       s.runs_since_maintenance, s.scrap_count, s.maintenance_every,
       (select count(*) from machine_run_outcome o where o.machine_id = s.machine_id) as runs,
       coalesce((select string_agg(a.op_type, ',' order by a.op_type) from accept_types a
                 where a.machine_id = s.machine_id), '') as accepts
  from machine_status s where s.machine_id = any(%s)
"""
LAST_RUNS_SQL = """
select distinct on (machine_id) machine_id, machine_run_id, ack_code, note, ended_at
  from machine_run_outcome where machine_id = any(%s) order by machine_id, ended_at desc
"""
RESULTS_SQL = """
select machine_id, param, value from machine_run_result
 where (machine_run_id, machine_id) in (select * from unnest(%s::bigint[], %s::text[])) order by param
"""
ALARMS_SQL = """
select a.alarm_no, a.alarm_id, a.machine_id, a.alarm_text, a.raised_by, a.raised_at,
       coalesce(d.severity, 'warning') as severity
  from alarms a left join alarm_description d using (alarm_id) where a.cleared_at is null order by a.alarm_no
"""
LOTS_SQL = """
select s.entity_id, s.lot_id, s.state, s.reason, s.updated_at, l.product_id, l.work_order_id, l.owner,
       l.priority, l.quantity
  from lot_status s join lots l using (lot_id) join lot_entities e using (entity_id)
 where e.destroyed_at is null
   and (s.state not in ('exported', 'failed') or s.updated_at > now() - make_interval(secs => %s))
"""


def rows(cur: Any, sql: str, *params: Any) -> list[dict[str, Any]]:
    """The rows of one query as dicts by column name."""
    cur.execute(sql, params)
    cols = [d.name for d in cur.description or []]
    return [dict(zip(cols, r)) for r in cur.fetchall()]
