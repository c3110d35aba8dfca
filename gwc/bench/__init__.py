"""The benchmarks behind `gwc bench`, and the statistics they share."""

from __future__ import annotations

import statistics
from collections.abc import Sequence


def cpu_s(pid: int) -> float:
    """CPU time process `pid` has had so far, in seconds (ns resolution: /proc/PID/schedstat)."""
    with open(f"/proc/{pid}/schedstat") as f:
        return int(f.read().split()[0]) / 1e9


def percentile(values: Sequence[float], p: float) -> float:
    """The p-th percentile (0-100) by nearest rank; NaN for no values."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    k = max(0, min(len(ordered) - 1, round(p / 100 * len(ordered) + 0.5) - 1))
    return ordered[k]


def summary(values: Sequence[float]) -> dict[str, float]:
    """Median, p99, mean, min, max and count of a sample."""
    if not values:
        return {
            "n": 0,
            "median": float("nan"),
            "p99": float("nan"),
            "mean": float("nan"),
            "min": float("nan"),
            "max": float("nan"),
        }
    return {
        "n": len(values),
        "median": statistics.median(values),
        "p99": percentile(values, 99),
        "mean": statistics.fmean(values),
        "min": min(values),
        "max": max(values),
    }
