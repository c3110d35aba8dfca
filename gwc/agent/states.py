"""Process states of a supervised module, after supervisor's states.py, and the moves between them.

STOPPED --start--> STARTING --ready--> RUNNING
STARTING --died/not ready--> BACKOFF --delay--> STARTING      (or FATAL after too many tries)
RUNNING --died--> STARTING (at once, if it had run `start_secs`) or BACKOFF (a crash loop)
any live state --stop--> STOPPING --died--> STOPPED
STARTING, RUNNING --ended of itself, its work done (a lot script)--> STOPPED
FATAL --start (operator)--> STARTING
"""

from __future__ import annotations

import enum


class ProcessState(enum.Enum):
    STOPPED = "STOPPED"  # not running, and not to be restarted (never started, or stopped on purpose)
    STARTING = "STARTING"  # spawned; not yet proven ready (on the bus, STARTUP done)
    RUNNING = "RUNNING"  # ready; a death now is a failure to announce and repair
    BACKOFF = "BACKOFF"  # died while starting (or soon after): waiting before the next try
    STOPPING = "STOPPING"  # told to stop (SIGTERM, then SIGKILL after the grace period)
    FATAL = "FATAL"  # failed too often in its start window: left down, alarm raised

    def __str__(self) -> str:
        return self.value


MOVES: dict[ProcessState, frozenset[ProcessState]] = {
    ProcessState.STOPPED: frozenset({ProcessState.STARTING}),
    ProcessState.STARTING: frozenset(
        {ProcessState.RUNNING, ProcessState.BACKOFF, ProcessState.STOPPING, ProcessState.FATAL, ProcessState.STOPPED}
    ),
    ProcessState.RUNNING: frozenset(
        {ProcessState.STARTING, ProcessState.BACKOFF, ProcessState.STOPPING, ProcessState.FATAL, ProcessState.STOPPED}
    ),
    ProcessState.BACKOFF: frozenset({ProcessState.STARTING, ProcessState.STOPPED, ProcessState.FATAL}),
    ProcessState.STOPPING: frozenset({ProcessState.STOPPED}),
    ProcessState.FATAL: frozenset({ProcessState.STARTING, ProcessState.STOPPED}),
}
LIVE = frozenset(
    {ProcessState.STARTING, ProcessState.RUNNING, ProcessState.STOPPING}
)  # a process exists in these states


class BadMove(RuntimeError):
    """A state change the table above does not allow: a bug in the agent, never an outside input."""
