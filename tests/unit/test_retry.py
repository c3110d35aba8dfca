"""The one deadline and backoff helper (gwc/retry.py): bounded by tries, by time, or by neither."""

from __future__ import annotations

import asyncio
import time

import pytest

from gwc.retry import Backoff, Deadline


def test_deadline_counts_down_on_the_monotonic_clock_and_never_ends_when_none() -> None:
    d = Deadline(0.05)
    assert 0 < d.left() <= 0.05 and not d.expired
    assert d.cap(10.0) <= 0.05 and d.cap(0.01) == 0.01
    time.sleep(0.06)
    assert d.expired and d.left() == 0.0
    assert Deadline(None).left() == float("inf") and not Deadline(None).expired
    assert Deadline(-1).expired


def test_backoff_doubles_to_its_ceiling_and_stops_after_its_attempts() -> None:
    b = Backoff(0.1, 0.3, attempts=5)
    assert [b.next() for _ in range(5)] == [0.1, 0.2, 0.3, 0.3, None]
    assert b.tries == 5


def test_backoff_within_a_deadline_never_pauses_past_it() -> None:
    b = Backoff(10.0, 10.0, within=0.05)
    pause = b.next()
    assert pause is not None and pause <= 0.05
    time.sleep(pause)
    assert b.next() is None


def test_backoff_shares_a_deadline_and_jitters_within_its_fraction() -> None:
    d = Deadline(60)
    pauses = [Backoff(1.0, 1.0, within=d, jitter=0.5).next() for _ in range(50)]
    assert all(p is not None and 0.5 <= p <= 1.5 for p in pauses) and len(set(pauses)) > 1


def test_without_bounds_backoff_goes_on() -> None:
    b = Backoff(0.01, 0.02)
    assert all(b.next() is not None for _ in range(1000))


@pytest.mark.parametrize("is_async", [False, True])
def test_sleep_and_asleep_pause_alike_and_say_when_to_stop(is_async: bool) -> None:
    b = Backoff(0.02, 0.02, attempts=2)
    started = time.monotonic()
    slept = [asyncio.run(b.asleep()) if is_async else b.sleep() for _ in range(3)]
    assert slept == [True, False, False]
    assert 0.015 <= time.monotonic() - started < 0.5
