"""What the benchmarks read of a cell's logs: a Figure 2 log's entries with their times, a lot's phases
from the named events its script left (gwc/lot/events.py), and each lot script's whole CPU as its
agent logged it when it reaped the script."""

from __future__ import annotations

import itertools
import re
from datetime import datetime
from pathlib import Path
from typing import Any

from gwc.lot.events import Phase

PHASES = [p.value for p in Phase]
STAMP = re.compile(r"\| Date (\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3}) \|.*?\| (?:Note|Warning|Error|Trace): (.*)$")
REAPED = re.compile(r"(lot:\d+): RUNNING -> STOPPED \(exited 0, (\d+) ms of CPU")  # the agent's log


def log_events(path: Path) -> list[tuple[float, str]]:
    """(epoch seconds, message) of every entry of a Figure 2 log."""
    out: list[tuple[float, str]] = []
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return out
    for line in lines:
        m = STAMP.search(line)
        if m:
            out.append((datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S.%f").timestamp(), m.group(2)))
    return out


def phases(events: list[list[Any]]) -> dict[str, float]:
    """Seconds between the marks of a lot's (first) operation: queued->bound, bound->setup, ..., from
    its named events ([phase, epoch seconds, machine] each)."""
    marks: dict[str, float] = {}
    for phase, at, _machine in events:
        marks.setdefault(phase, at)
    return {f"{a}->{b}": marks[b] - marks[a] for a, b in itertools.pairwise(PHASES) if a in marks and b in marks}


def bound_to(events: list[list[Any]], machine: str, since: float) -> float | None:
    """When the lot was given `machine` (the first machine of a reservation) at or after `since`."""
    return next((at for phase, at, m in events if phase == Phase.BOUND and m == machine and at >= since), None)


def script_cpu(log_dir: Path, entities: list[int]) -> list[float]:
    """Each lot script's whole CPU (ms), start-up included, as its agent logged it when it reaped it."""
    wanted = {f"lot:{e}" for e in entities}
    out = []
    for log in log_dir.glob("agent-*.log"):
        for m in REAPED.finditer(log.read_text(errors="replace")):
            if m.group(1) in wanted:
                out.append(float(m.group(2)))
    return out
