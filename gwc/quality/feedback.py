"""Run-to-run feedback: an EWMA controller that sets the next run's offset from earlier parts' measurements.

The model (docs/quality.md): a part's feature comes out as nominal + offset + d, where d (the
machine's bias and its tool's wear) moves slowly. Each measured part of an earlier run tells d:
d = (measured - nominal) - the offset that run was given. The controller keeps an EWMA of it,

    estimate = weight * (deviation - offset_used) + (1 - weight) * estimate      (0 at a tool change)

and gives the next run offset = -estimate, moved at most `step_limit` from the last offset used and
never past `total_limit`. An estimate that needs more than `total_limit` is a worn tool.
The controller's state is this history, stored with the runs (run_features): recomputed from the
database at every run, it survives any process.
"""

from __future__ import annotations

from dataclasses import dataclass

from gwc.quality.recipe import FeedbackSettings


@dataclass(frozen=True)
class Advice:
    offset: float  # what the next run is given
    needed: float  # what the estimate asks for (past total_limit: the tool is worn out)
    worn: bool
    parts: int  # measured parts the estimate is made of (since the tool change)


def clamp(x: float, limit: float) -> float:
    return max(-limit, min(limit, x))


def next_offset(history: list[tuple[float, float]], settings: FeedbackSettings) -> Advice:
    """history: (offset used, measured - nominal) of each measured run since the tool change, oldest first."""
    estimate, last = 0.0, 0.0
    for used, deviation in history:
        estimate = settings.weight * (deviation - used) + (1 - settings.weight) * estimate
        last = used
    needed = -estimate
    target = clamp(needed, settings.total_limit)
    offset = last + clamp(target - last, settings.step_limit)
    return Advice(round(offset, 6), round(needed, 6), abs(needed) > settings.total_limit, len(history))


def feed_forward(offset_used: float, deviation: float) -> float:
    """The offset a part sent back for re-milling is given: the one it was made with, less what its own
    measurement found it off by."""
    return round(offset_used - deviation, 6)
