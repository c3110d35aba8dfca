"""The event loop every GWC process runs its bus on: uvloop's (libuv's loop, in C).

asyncio's own loop is Python: each turn (poll, timers, ready callbacks) costs microseconds of
interpreter work, and a message delivered to a waiting task takes two turns and two epoll calls a
side. On the bus's round trip that was about an eighth of both sides' CPU (docs/performance.md,
"The bus"); uvloop runs the same asyncio API in C. One place, so that every process (modules, the
agent, BlockingBus threads, the benches) runs the loop the benchmarks measure.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, TypeVar

import uvloop

T = TypeVar("T")


def new_loop() -> asyncio.AbstractEventLoop:
    """A new event loop of the kind the cell runs (not set as the thread's current loop)."""
    return uvloop.new_event_loop()


def run(main: Coroutine[Any, Any, T]) -> T:
    """asyncio.run(main) on the cell's kind of loop."""
    with asyncio.Runner(loop_factory=new_loop) as runner:
        return runner.run(main)
