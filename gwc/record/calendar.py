"""Planned production time: a shift calendar (cell.toml [record.calendars]) turned into intervals.

OEE's availability divides run time by planned time, and a machine stopped outside planned time
is non-scheduled (SEMI E10), not down: both need "which of [since, until) was planned".
"""

from __future__ import annotations

from datetime import datetime, timedelta
from zoneinfo import ZoneInfo

from gwc.config import Calendar

Interval = tuple[datetime, datetime]


def planned_intervals(cal: Calendar, since: datetime, until: datetime, timezone: str = "UTC") -> list[Interval]:
    """The planned parts of [since, until), merged and in order (aware datetimes in, aware out)."""
    if until <= since:
        return []
    if cal.always:
        return [(since, until)]
    tz = ZoneInfo(timezone)
    first = since.astimezone(tz).date() - timedelta(days=1)  # an overnight shift of the day before
    last = until.astimezone(tz).date()
    out: list[Interval] = []
    day = first
    while day <= last:
        midnight = datetime(day.year, day.month, day.day, tzinfo=tz)
        for s in cal.shifts:
            if day.weekday() not in s.days:
                continue
            start = midnight + timedelta(minutes=s.start)
            end = midnight + timedelta(minutes=s.end if s.end > s.start else s.end + 24 * 60)
            a, b = max(start, since), min(end, until)
            if a < b:
                out.append((a, b))
        day += timedelta(days=1)
    out.sort()
    merged: list[Interval] = []
    for a, b in out:
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def is_planned(cal: Calendar, at: datetime, timezone: str = "UTC") -> bool:
    """Whether the instant `at` is planned production time."""
    return cal.always or bool(planned_intervals(cal, at, at + timedelta(microseconds=1), timezone))


def overlap(a: Interval, spans: list[Interval]) -> float:
    """Seconds of interval `a` inside the (ordered, disjoint) `spans`."""
    total = 0.0
    for s, e in spans:
        lo, hi = max(a[0], s), min(a[1], e)
        if lo < hi:
            total += (hi - lo).total_seconds()
    return total
