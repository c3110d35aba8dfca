"""One module the agent supervises: its process, its state, and how often it failed.

The agent learns of a death the moment it happens: every process it watches has a pidfd
(pidfd_open(2)) registered with the event loop, which becomes readable when the process exits.
That works for processes the agent spawned (then reaped for their exit status) and for ones it
adopted from an agent before it (their status is the kernel's parent's to read, so unknown here).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import time
from collections.abc import Callable
from datetime import datetime
from typing import Protocol

from gwc.agent.states import LIVE, MOVES, BadMove, ProcessState
from gwc.cell import Proc


class Process(Protocol):
    """A process the agent started and reaps: a Popen (exec'd), or a forked lot script (gwc.lot.run.Forked)."""

    pid: int

    def wait(self) -> int: ...


class Child:
    """One supervised module. Its state changes only through change_state(), which logs every move."""

    def __init__(self, proc: Proc, log: logging.Logger) -> None:
        self.proc = proc
        self.log = log
        self.state = ProcessState.STOPPED
        self.popen: Process | None = None  # None for an adopted process
        self.pid: int | None = None
        self.started_at = 0.0  # monotonic: when the current process was spawned (or adopted)
        self.since = ""  # wall clock of the same, for people
        self.running_at = 0.0  # monotonic: when it was last found ready
        self.died_at: float | None = None  # monotonic: when its last process was seen to end
        self.restarts = 0  # restarts the agent made after a death (not operator starts)
        self.fails = 0  # deaths in a row before the module ran `start_secs`
        self.last_exit = ""  # how the last process ended
        self.last_code: int | None = None  # its exit status (negative: the signal); None if unknown (adopted)
        self.ready: asyncio.Task[None] | None = None  # the readiness probe of the current process
        self.boost_until = 0.0  # monotonic: its start's boost lasts past ready until then (a takeover)
        self.retry: asyncio.TimerHandle | None = None  # the BACKOFF timer
        self.changed = asyncio.Event()  # set at every state change (waiters clear it themselves)
        self._pidfd: int | None = None

    @property
    def name(self) -> str:
        return self.proc.name

    def change_state(self, new: ProcessState, why: str = "") -> None:
        """The one place a state changes: checked against MOVES and logged."""
        old = self.state
        if new != old and new not in MOVES[old]:
            raise BadMove(f"{self.name}: {old} -> {new} is not a move the agent makes ({why})")
        self.state = new
        if new == ProcessState.RUNNING:
            self.running_at = time.monotonic()
        level = logging.ERROR if new == ProcessState.FATAL else logging.INFO
        pid = f" pid {self.pid}" if self.pid and new in LIVE else ""
        self.log.log(level, "%s: %s -> %s%s%s", self.name, old, new, pid, f" ({why})" if why else "")
        self.changed.set()

    # ----------------------------------------------------------------- the process

    def attach(
        self,
        pid: int,
        popen: Process | None,
        on_exit: Callable[[Child], None],
        still_ours: Callable[[], bool] = lambda: True,
    ) -> bool:
        """Watch process `pid` (spawned, or adopted when popen is None); False if it is already gone.

        `still_ours` is asked once the pidfd is open: an adopted pid read from a pid file may have
        been reused by another process in between, and the pidfd must be the module's own."""
        try:
            fd = os.pidfd_open(pid)
        except ProcessLookupError:
            return False
        if not still_ours():
            os.close(fd)
            return False
        self.popen, self.pid, self._pidfd = popen, pid, fd
        self.started_at = time.monotonic()
        self.since = datetime.now().isoformat(" ", "seconds")
        asyncio.get_running_loop().add_reader(fd, on_exit, self)
        return True

    def reap(self) -> str:
        """The process ended (its pidfd is readable): stop watching, reap it; how it ended."""
        if self._pidfd is not None:
            asyncio.get_running_loop().remove_reader(self._pidfd)
            os.close(self._pidfd)
            self._pidfd = None
        how, code = "exited (adopted: status unknown)", None
        if self.popen is not None:
            code = self.popen.wait()  # already dead: does not block
            how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exited {code}"
        self.last_code = code
        self.popen = None
        self.died_at = time.monotonic()
        self.last_exit = how
        return how

    def signal_group(self, sig: signal.Signals) -> None:
        """Signal the module's process group (it leads one: its helpers go with it)."""
        if self.pid is None or self._pidfd is None:
            return
        try:
            os.killpg(self.pid, sig)
        except ProcessLookupError:
            pass

    def uptime(self) -> float | None:
        return time.monotonic() - self.started_at if self.state in LIVE and self.pid else None

    def row(self) -> dict[str, object]:
        up = self.uptime()
        return {
            "module": self.name,
            "state": self.state.value,
            "pid": self.pid if self.state in LIVE else None,
            "uptime": None if up is None else round(up, 1),
            "since": self.since if self.state in LIVE else None,
            "restarts": self.restarts,
            "last_exit": self.last_exit or None,
            # CLOCK_MONOTONIC, the same in every process of the host: a kill's time can be set beside them.
            "died_at": self.died_at,
            "running_at": self.running_at or None,
        }
