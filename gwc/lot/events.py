"""Named events of an operation's life, for whoever times it (`gwc bench cell`), not for readers of
its log: each is attached to the lot library's log line that marks it (`extra=event(...)`), so the
wording of that line can change freely and the benchmark still finds the moment.

A `Recorder` on an entity's logger keeps them (a lot script that wants its own timings, as the
soak's does: gwc/lot/scripts/soak.py); no recorder, no cost beyond the log line itself.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import StrEnum
from typing import Any


class Phase(StrEnum):
    """The marks of one operation, in the order they come."""

    QUEUED = "queued"  # MSCHED queued the request (each alternative's)
    BOUND = "bound"  # MSCHED reserved machines: `machine` is the first of them
    SETUP = "setup"  # SETUP_RUN asked of the machine's WC
    STARTED = "started"  # the WC started the run
    COMPLETE = "complete"  # every machine of the run reported its result
    UNRESERVED = "unreserved"  # the machines were given back


def event(phase: Phase, machine: str | None = None) -> dict[str, Any]:
    """The `extra` of the log call that marks `phase`."""
    return {"event": phase, "machine": machine}


@dataclass(frozen=True)
class Mark:
    phase: Phase
    at: float  # epoch seconds, the log record's own time
    machine: str | None = None


class Recorder(logging.Handler):
    """Keeps the events a logger's records carry, in the order they came."""

    def __init__(self) -> None:
        super().__init__(logging.NOTSET)
        self.marks: list[Mark] = []

    def emit(self, record: logging.LogRecord) -> None:
        phase = getattr(record, "event", None)
        if phase is not None:
            self.marks.append(Mark(Phase(phase), record.created, getattr(record, "machine", None)))

    def as_list(self) -> list[list[Any]]:
        """[phase, at, machine] of each mark: what a timing file holds."""
        return [[m.phase.value, m.at, m.machine] for m in self.marks]


def record(log: logging.Logger) -> Recorder:
    """Start keeping the events `log` carries."""
    recorder = Recorder()
    log.addHandler(recorder)
    return recorder
