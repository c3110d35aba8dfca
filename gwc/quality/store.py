"""The quality reads (sql/070_quality.sql): a recipe's features and feedback, the feedback's history,
the control charts' points, the tool changes. Every function takes `read(sql, params) -> rows`, so a
lot script (OperationEntity.read) and the Human Interface (a connection) use the same SQL."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from gwc.quality.recipe import Feature, FeedbackSettings

Reader = Callable[[str, Sequence[Any]], list[tuple[Any, ...]]]


@dataclass(frozen=True)
class Point:
    """One measured feature of one part, charted under the machine and recipe that made the part."""

    machine_id: str
    recipe_id: str
    feature: str
    machine_run_id: int  # the measuring run
    made_by: int | None  # the run that made the part (None: measured where it was made)
    value: float
    nominal: float
    tol: float
    offset: float | None
    at: datetime


def features(read: Reader, recipe_id: str) -> list[Feature]:
    rows = read(
        "SELECT feature, nominal, tol FROM recipe_features WHERE recipe_id = %s AND approved ORDER BY feature",
        (recipe_id,),
    )
    return [Feature(str(f), float(n), float(t)) for f, n, t in rows]


def feedback(read: Reader, recipe_id: str) -> FeedbackSettings | None:
    rows = read(
        "SELECT weight, step_limit, total_limit FROM recipe_feedback WHERE recipe_id = %s AND approved LIMIT 1",
        (recipe_id,),
    )
    if not rows or not 0 < float(rows[0][0]) <= 1:
        return None
    return FeedbackSettings(*(float(v) for v in rows[0]))


# The machine's last tool change: the operator's confirmation (`gwc tool change`) or a maintenance
# (MAINT_DONE, in the production record), whichever is later.
LAST_CHANGE = (
    "(SELECT max(t) FROM (SELECT max(changed_at) AS t FROM tool_changes WHERE machine_id = %s "
    "UNION ALL SELECT max(at) FROM machine_state_history WHERE machine_id = %s AND cause = 'maintenance') c)"
)


def tool_changes(read: Reader, machine_id: str) -> int:
    """The machine's last tool change (or maintenance) as milliseconds since the epoch, 0 if none: the run
    sheet's TOOL, which only grows, so that a simulated mill sees each change once."""
    rows = read(
        f"SELECT coalesce(floor(extract(epoch FROM {LAST_CHANGE}) * 1000), 0)::bigint", (machine_id, machine_id)
    )
    return int(rows[0][0])


def history(read: Reader, machine_id: str, recipe_id: str, feature: str, limit: int = 100) -> list[tuple[float, float]]:
    """(offset used, measured - nominal) of the machine's first cuts with the recipe since its last tool
    change, each paired with the latest measurement of its part; oldest first."""
    rows = read(
        "SELECT mk.offset_used, m.measured - m.nominal FROM run_features mk "
        "JOIN LATERAL (SELECT measured, nominal FROM run_features m WHERE m.workpiece = mk.machine_run_id "
        "  AND m.feature = mk.feature AND m.measured IS NOT NULL ORDER BY m.at DESC LIMIT 1) m ON true "
        "WHERE mk.machine_id = %s AND mk.recipe_id = %s AND mk.feature = %s AND mk.workpiece IS NULL "
        "  AND mk.offset_used IS NOT NULL AND mk.measured IS NULL "
        f"  AND mk.at > coalesce({LAST_CHANGE}, '-infinity') "
        "ORDER BY mk.machine_run_id DESC LIMIT %s",
        (machine_id, recipe_id, feature, machine_id, machine_id, limit),
    )
    return [(float(u), float(e)) for u, e in reversed(rows)]


def points(
    read: Reader,
    machine_id: str | None = None,
    feature: str | None = None,
    recipe_id: str | None = None,
    limit: int = 500,
) -> list[Point]:
    """Measured features of first cuts (a re-milled part's later measurements are not the process's),
    under the machine and recipe that made each part; oldest first, the last `limit` of each chart."""
    rows = read(
        "SELECT * FROM (SELECT coalesce(mk.machine_id, m.machine_id) AS machine, "
        "  coalesce(mk.recipe_id, m.recipe_id) AS recipe, m.feature, m.machine_run_id, mk.machine_run_id, "
        "  m.measured, m.nominal, m.tol, mk.offset_used, m.at, "
        "  row_number() OVER (PARTITION BY coalesce(mk.machine_id, m.machine_id), "
        "    coalesce(mk.recipe_id, m.recipe_id), m.feature ORDER BY m.at DESC) AS n "
        "FROM run_features m LEFT JOIN run_features mk ON mk.machine_run_id = m.workpiece "
        "  AND mk.feature = m.feature AND mk.measured IS NULL "
        "WHERE m.measured IS NOT NULL AND (m.workpiece IS NULL OR mk.workpiece IS NULL)) p "
        "WHERE n <= %s AND (%s::text IS NULL OR machine = %s) AND (%s::text IS NULL OR feature = %s) "
        "  AND (%s::text IS NULL OR recipe = %s) "
        "ORDER BY machine, recipe, feature, at",
        (limit, machine_id, machine_id, feature, feature, recipe_id, recipe_id),
    )
    return [
        Point(
            str(m),
            str(r),
            str(f),
            int(run),
            None if mk is None else int(mk),
            float(v),
            float(n),
            float(t),
            None if o is None else float(o),
            at,
        )
        for m, r, f, run, mk, v, n, t, o, at, _ in rows
    ]


def run_features(read: Reader, machine_run_id: int) -> list[dict[str, Any]]:
    """Every feature stored with a run (its measurements, its offsets), for genealogy and `gwc lots`."""
    rows = read(
        "SELECT machine_id, recipe_id, feature, measured, nominal, tol, offset_used, workpiece, in_tol "
        "FROM run_features WHERE machine_run_id = %s ORDER BY machine_id, feature",
        (machine_run_id,),
    )
    keys = ("machine_id", "recipe_id", "feature", "measured", "nominal", "tol", "offset", "workpiece", "in_tol")
    return [dict(zip(keys, r, strict=True)) for r in rows]


def pending_alarm(read: Reader, machine_id: str, alarm_id: str, text_like: str = "%") -> bool:
    rows = read(
        "SELECT 1 FROM alarms WHERE machine_id = %s AND alarm_id = %s AND cleared_at IS NULL "
        "AND coalesce(alarm_text, '') LIKE %s LIMIT 1",
        (machine_id, alarm_id, text_like),
    )
    return bool(rows)


@dataclass(frozen=True)
class Yield:
    machine_id: str
    parts: int  # first cuts measured, of the last `window`
    good: int  # of them, every feature within tolerance

    @property
    def rate(self) -> float:
        """good / parts; a machine never measured counts as perfect, so that it is tried."""
        return self.good / self.parts if self.parts else 1.0


def yields(read: Reader, op_type: str, machines: Sequence[str], window: int = 20) -> dict[str, Yield]:
    """Each machine's yield for the operation: of its last `window` first cuts with a recipe for op_type
    (measured), how many had every feature within tolerance."""
    rows = read(
        "SELECT machine_id, count(*), count(*) FILTER (WHERE ok) FROM ("
        "  SELECT mk.machine_id, mk.machine_run_id, bool_and(m.in_tol) AS ok, "
        "    row_number() OVER (PARTITION BY mk.machine_id ORDER BY mk.machine_run_id DESC) AS n "
        "  FROM run_features mk JOIN run_features m ON m.workpiece = mk.machine_run_id AND m.feature = mk.feature "
        "    AND m.measured IS NOT NULL "
        "  WHERE mk.machine_id = ANY(%s) AND mk.workpiece IS NULL AND mk.measured IS NULL "
        "    AND EXISTS (SELECT 1 FROM op_machine_recipe o WHERE o.machine_id = mk.machine_id "
        "      AND o.recipe_id = mk.recipe_id AND o.op_type = %s) "
        "  GROUP BY mk.machine_id, mk.machine_run_id) p "
        "WHERE n <= %s GROUP BY machine_id",
        (list(machines), op_type, window),
    )
    found = {str(m): Yield(str(m), int(n), int(g)) for m, n, g in rows}
    return {m: found.get(m, Yield(m, 0, 0)) for m in machines}
