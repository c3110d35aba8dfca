"""Statistical process control: an individuals and moving-range chart, the Western Electric rules, Cp, Cpk.

Pure arithmetic on a series of measurements (oldest first); gwc/quality/store.py reads the series,
gwc/quality/lot.py raises the alarms, `gwc spc` shows the charts (docs/quality.md).

Limits come from the first `baseline` points of the series (phase I): centre line their mean, sigma
their mean moving range / d2 (1.128); the rules are tried on every later point (phase II).
"""

from __future__ import annotations

import itertools
import math
import statistics
from dataclasses import dataclass, field

from gwc.config import Config
from gwc.errors import ConfigError

D2 = 1.128  # d2 for moving ranges of two
D4 = 3.267  # the moving-range chart's upper limit factor

RULES: dict[str, str] = {
    "WE1": "one point beyond 3 sigma",
    "WE2": "2 of 3 points beyond 2 sigma on one side",
    "WE3": "4 of 5 points beyond 1 sigma on one side",
    "WE4": "8 points in a row on one side of the centre",
    "N3": "6 points in a row rising or falling",
}
DEFAULT_RULES = ("WE1", "WE2", "WE3", "WE4")


@dataclass(frozen=True)
class Limits:
    center: float
    sigma: float
    mr_bar: float

    @property
    def ucl(self) -> float:
        return self.center + 3 * self.sigma

    @property
    def lcl(self) -> float:
        return self.center - 3 * self.sigma

    @property
    def mr_ucl(self) -> float:
        return D4 * self.mr_bar


@dataclass(frozen=True)
class Violation:
    index: int  # the point (0 = oldest) at which the rule was broken
    rule: str

    @property
    def text(self) -> str:
        return f"{self.rule} ({RULES.get(self.rule, self.rule)})"


@dataclass
class Chart:
    feature: str
    values: list[float]
    limits: Limits | None
    violations: list[Violation] = field(default_factory=list)
    cp: float | None = None
    cpk: float | None = None


def settings(cfg: Config) -> tuple[tuple[str, ...], int, int]:
    """etc/cell.toml [quality]: spc_rules (which rules alarm), spc_baseline (points the limits come
    from), spc_window (points charted); ConfigError for a wrong one."""
    section = cfg.raw.get("quality", {})
    rules = tuple(section.get("spc_rules", DEFAULT_RULES))
    baseline, window = section.get("spc_baseline", 20), section.get("spc_window", 100)
    if set(rules) - set(RULES):
        raise ConfigError(f"[quality] spc_rules: unknown rule(s); known: {', '.join(RULES)}")
    if not isinstance(baseline, int) or not isinstance(window, int) or not 2 <= baseline < window:
        raise ConfigError("[quality] spc_baseline and spc_window: counts of points, 2 <= baseline < window")
    return rules, baseline, window


def limits(values: list[float], baseline: int) -> Limits | None:
    """Phase I limits from the first `baseline` points (at least 2), or None with too few."""
    base = values[:baseline]
    if len(base) < 2:
        return None
    mr = [abs(b - a) for a, b in itertools.pairwise(base)]
    mr_bar = statistics.fmean(mr)
    sigma = mr_bar / D2
    if sigma <= 0:
        sigma = statistics.pstdev(base) or 1e-9
    return Limits(statistics.fmean(base), sigma, mr_bar)


def _zone(x: float, lim: Limits) -> float:
    return (x - lim.center) / lim.sigma


def broken_at(values: list[float], lim: Limits, i: int, rules: tuple[str, ...]) -> list[str]:
    """The rules broken by the window that ends at point i."""
    z = [_zone(x, lim) for x in values[: i + 1]]
    out = []

    def same_side(win: list[float], beyond: float, need: int) -> bool:
        return sum(1 for v in win if v > beyond) >= need or sum(1 for v in win if v < -beyond) >= need

    if "WE1" in rules and abs(z[i]) > 3:
        out.append("WE1")
    if "WE2" in rules and len(z) >= 3 and abs(z[i]) > 2 and same_side(z[i - 2 : i + 1], 2, 2):
        out.append("WE2")
    if "WE3" in rules and len(z) >= 5 and abs(z[i]) > 1 and same_side(z[i - 4 : i + 1], 1, 4):
        out.append("WE3")
    if (
        "WE4" in rules
        and len(z) >= 8
        and (all(v > 0 for v in z[i - 7 : i + 1]) or all(v < 0 for v in z[i - 7 : i + 1]))
    ):
        out.append("WE4")
    if "N3" in rules and len(z) >= 6:
        w = values[i - 5 : i + 1]
        d = [b - a for a, b in itertools.pairwise(w)]
        if all(x > 0 for x in d) or all(x < 0 for x in d):
            out.append("N3")
    return out


def capability(values: list[float], lsl: float, usl: float) -> tuple[float | None, float | None]:
    """(Cp, Cpk) of the points against the tolerance, with the standard deviation of all of them (so a
    drift counts against the process: strictly Pp and Ppk); None with fewer than 2 points."""
    if len(values) < 2:
        return None, None
    s = statistics.stdev(values)
    if s <= 0:
        return math.inf, math.inf
    mean = statistics.fmean(values)
    return (usl - lsl) / (6 * s), min(usl - mean, mean - lsl) / (3 * s)


def chart(
    feature: str,
    values: list[float],
    lsl: float,
    usl: float,
    rules: tuple[str, ...] = DEFAULT_RULES,
    baseline: int = 20,
) -> Chart:
    """The chart of a feature: limits from the baseline, the rules broken after it, Cp and Cpk."""
    lim = limits(values, baseline)
    found = []
    if lim is not None:
        for i in range(min(baseline, len(values)), len(values)):
            found += [Violation(i, r) for r in broken_at(values, lim, i, rules)]
    cp, cpk = capability(values, lsl, usl)
    return Chart(feature, values, lim, found, cp, cpk)


def first_alarm(c: Chart) -> Violation | None:
    return c.violations[0] if c.violations else None


def drawing(c: Chart, width: int = 60, height: int = 9) -> list[str]:
    """The chart as text for a console: one column per point (the last `width`), the limits as rules."""
    pts = c.values[-width:]
    if c.limits is None or not pts:
        return [f"{c.feature}: {len(pts)} point(s), too few for limits"]
    lim = c.limits
    lo = min(min(pts), lim.lcl)
    hi = max(max(pts), lim.ucl)
    span = (hi - lo) or 1.0

    def row(v: float) -> int:
        return round((hi - v) / span * (height - 1))

    grid = [[" "] * len(pts) for _ in range(height)]
    for name, v in (("-", lim.ucl), ("-", lim.lcl), (".", lim.center)):
        for x in range(len(pts)):
            grid[row(v)][x] = name
    offset = len(c.values) - len(pts)
    bad = {v.index for v in c.violations}
    for x, v in enumerate(pts):
        grid[row(v)][x] = "x" if x + offset in bad else "o"
    labels = {
        row(lim.ucl): f"UCL {lim.ucl:.4f}",
        row(lim.center): f"CL  {lim.center:.4f}",
        row(lim.lcl): f"LCL {lim.lcl:.4f}",
    }
    return [f"{''.join(r)}  {labels.get(i, '')}".rstrip() for i, r in enumerate(grid)]
