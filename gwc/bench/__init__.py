"""The benchmarks behind `gwc bench`, and the statistics they share."""

from __future__ import annotations

import math
import os
import statistics
from collections.abc import Sequence


def pin_cpu(which: int, cpus: Sequence[int] | None = None) -> None:
    """Put this process on CPU `which` of `cpus` (default: those it may use now), when there are two or
    more. The two ends of a ping-pong benchmark each take their own, in every mode alike: left to
    itself the kernel sometimes wakes both on one CPU, and a round trip then costs what that placement
    costs, not what the code does (a bare posix-ipc round trip on this VM: 3 us on one CPU, 66-76 us
    across two, the same code in runs minutes apart)."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    if len(cpus) >= 2:
        os.sched_setaffinity(0, {cpus[which % len(cpus)]})


def cpu_s(pid: int) -> float:
    """CPU time process `pid` has had so far, in seconds (ns resolution: /proc/PID/schedstat)."""
    with open(f"/proc/{pid}/schedstat") as f:
        return int(f.read().split()[0]) / 1e9


def reaped_cpu_s(pid: int) -> float:
    """CPU time of the children process `pid` has reaped, in seconds (/proc/PID/stat cutime + cstime, in
    clock ticks): what processes that came and went between two samples of cpu_s spent."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    return (int(fields[13]) + int(fields[14])) / os.sysconf("SC_CLK_TCK")


def percentile(values: Sequence[float], p: float) -> float:
    """The p-th percentile (0-100) by nearest rank; NaN for no values."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    k = max(0, min(len(ordered) - 1, math.ceil(p / 100 * len(ordered)) - 1))  # rank ceil(p% of n)
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


def brief(s: dict[str, float]) -> str:
    """A summary() in one line: median, p99 and count."""
    return f"median {s['median']:.1f}, p99 {s['p99']:.1f}, n {s['n']}"
