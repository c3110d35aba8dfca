"""The scheduling policies: FIFO, and priority with ageing; the cell's configuration chooses."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from gwc.errors import ConfigError
from gwc.msched.policy import Candidate, Fifo, Priority, make_policy
from tests.conftest import make_config

NOW = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)


def cand(key: int, seq: int, priority: int = 20, waited_s: float = 0.0) -> Candidate:
    return Candidate(key, key, "dummy_op", priority, seq, NOW - timedelta(seconds=waited_s), ("wc1",))


def test_fifo_orders_by_arrival_whatever_the_priority() -> None:
    cs = [cand(3, 30, priority=1), cand(1, 10, priority=50), cand(2, 20)]
    assert [c.request_key for c in Fifo().order(cs, NOW)] == [1, 2, 3]


def test_priority_serves_the_most_urgent_first_and_fifo_among_equals() -> None:
    cs = [cand(1, 10, priority=20), cand(2, 20, priority=5), cand(3, 30, priority=20), cand(4, 40, priority=5)]
    assert [c.request_key for c in Priority(ageing_s=60).order(cs, NOW)] == [2, 4, 1, 3]


def test_priority_ageing_lets_an_old_request_overtake_newer_urgent_ones() -> None:
    old = cand(1, 10, priority=30, waited_s=300)  # 300 s at one step per 10 s: effective 0
    urgent = cand(2, 20, priority=5)
    assert Priority(ageing_s=10).order([urgent, old], NOW)[0] is old
    assert Priority(ageing_s=1000).order([urgent, old], NOW)[0] is urgent


def test_nothing_starves_under_priority() -> None:
    """However urgent the newcomers, a waiting request comes first once it has waited long enough."""
    policy = Priority(ageing_s=2)
    low = cand(1, 1, priority=100, waited_s=0)
    served_at = None
    for t in range(0, 1000):
        newcomer = Candidate(1000 + t, 1000 + t, "dummy_op", 0, 1000 + t, NOW + timedelta(seconds=t), ("wc1",))
        if policy.order([newcomer, low], NOW + timedelta(seconds=t))[0] is low:
            served_at = t
            break
    assert served_at is not None and served_at <= 201


def test_config_chooses_the_policy(tmp_path: Path) -> None:
    assert isinstance(make_policy(make_config(tmp_path / "a", None)), Fifo)
    pri = make_policy(make_config(tmp_path / "b", None, cell={"policy": "priority"}, msched={"ageing_s": 7}))
    assert isinstance(pri, Priority) and pri.ageing_s == 7
    with pytest.raises(ConfigError):
        make_policy(make_config(tmp_path / "c", None, cell={"policy": "priority"}, msched={"ageing_s": 0}))
    with pytest.raises(ConfigError):
        make_config(tmp_path / "d", None, cell={"policy": "lifo"})
