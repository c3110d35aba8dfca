"""Deadlines and bounded backoff: how every wait is bounded and every retry loop is paced.

A `Deadline` is a point on time.monotonic() (never the wall clock, which jumps). A `Backoff` gives
the pauses between tries: short at first, growing to a ceiling, bounded by a number of tries, a
deadline, or both. The decision (pause how long, or give up) is `Backoff.next()`, written once;
sync and async loops differ only in how they sleep (`sleep()` blocks, `asleep()` awaits):

    backoff = Backoff(0.2, 2.0, within=60)
    while True:
        try:
            return ask()
        except Unanswered:
            if not backoff.sleep():  # or: `await backoff.asleep()`
                raise
"""

from __future__ import annotations

import asyncio
import math
import random
import time


class Deadline:
    """A moment `seconds` from now on the monotonic clock; None means never."""

    __slots__ = ("at",)

    def __init__(self, seconds: float | None) -> None:
        self.at = math.inf if seconds is None else time.monotonic() + max(0.0, seconds)

    def left(self) -> float:
        """Seconds until the deadline (0 once passed; inf for never)."""
        return max(0.0, self.at - time.monotonic())

    @property
    def expired(self) -> bool:
        return time.monotonic() >= self.at

    def cap(self, timeout: float) -> float:
        """`timeout`, shortened so that a wait of it ends by the deadline."""
        return min(timeout, self.left())

    def __repr__(self) -> str:
        return f"Deadline(left={self.left():.3f}s)"


class Backoff:
    """Pauses between tries: `first`, multiplied by `factor` up to `most`, each varied by +-`jitter`
    (a fraction, so that many askers do not retry in step).

    Bounded by `attempts` (tries in all, the first included) and/or `within` (seconds, or a
    Deadline shared with other waits); a pause never runs past the deadline. Unbounded if neither
    is given: for loops that end some other way (a module reconnecting to its database until it
    is back). `tries` counts the failed tries reported so far (the calls to next()).
    """

    def __init__(
        self,
        first: float = 0.2,
        most: float = 2.0,
        *,
        within: float | Deadline | None = None,
        attempts: int | None = None,
        factor: float = 2.0,
        jitter: float = 0.0,
    ) -> None:
        self.deadline = within if isinstance(within, Deadline) else Deadline(within)
        self.attempts = None if attempts is None else max(1, attempts)
        self.delay = first
        self.most = most
        self.factor = factor
        self.jitter = jitter
        self.tries = 0

    def next(self) -> float | None:
        """A try failed: the pause before the next one, or None when there is to be no next one."""
        self.tries += 1
        if self.attempts is not None and self.tries >= self.attempts:
            return None
        left = self.deadline.left()
        if left <= 0:
            return None
        pause = self.delay * (random.uniform(1 - self.jitter, 1 + self.jitter) if self.jitter else 1.0)
        self.delay = min(self.delay * self.factor, self.most)
        return min(pause, left)

    def sleep(self) -> bool:
        """Pause before the next try (blocking); False, at once, when there is to be none."""
        pause = self.next()
        if pause is None:
            return False
        time.sleep(pause)
        return True

    async def asleep(self) -> bool:
        """Pause before the next try (awaiting); False, at once, when there is to be none."""
        pause = self.next()
        if pause is None:
            return False
        await asyncio.sleep(pause)
        return True
