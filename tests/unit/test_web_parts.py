"""The web module's parts that need no cell: its settings, sessions and the login's lockout."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from gwc.errors import ConfigError
from gwc.users import Person, Role
from gwc.web.sessions import Lockout, Sessions
from gwc.web.settings import load_settings
from tests.conftest import make_config


def test_settings_are_checked_and_name_the_key(tmp_path: Path) -> None:
    s = load_settings(make_config(tmp_path / "a", None, web={"listen": "0.0.0.0:9443"}))
    assert (s.host, s.port, s.lockout_after) == ("0.0.0.0", 9443, 10)
    for bad, says in (
        ({"listen": "nowhere"}, "HOST:PORT"),
        ({"listen": "127.0.0.1:0"}, "HOST:PORT"),
        ({"lockout_after": 0}, "lockout_after"),
        ({"certificate": "x.pem"}, "certificate and key go together"),
        ({"colour": "red"}, "unknown key"),
    ):
        with pytest.raises(ConfigError, match=says):
            load_settings(make_config(tmp_path / str(len(says)), None, web=bad))


def test_a_session_ends_when_idle_too_long_or_at_logout(monkeypatch: Any) -> None:
    now = [1000.0]
    monkeypatch.setattr(time, "monotonic", lambda: now[0])
    sessions = Sessions(idle=60, longest=600)
    s = sessions.open(Person("ann", Role.operator, "web"))
    assert sessions.get(s.token) is s and len(s.csrf) >= 40 and s.csrf != s.token
    assert Sessions.csrf_ok(s, s.csrf) and not Sessions.csrf_ok(s, "x") and not Sessions.csrf_ok(s, None)
    now[0] += 59
    assert sessions.alive(s.token)  # looked at, not used (an event stream does this)
    assert sessions.get(s.token) is s  # used: idle again from now
    now[0] += 30
    assert sessions.alive(s.token)
    now[0] += 31
    assert not sessions.alive(s.token)
    assert sessions.get(s.token) is None
    t = sessions.open(Person("ann", Role.operator, "web"))
    for _ in range(10):
        now[0] += 55
        assert sessions.get(t.token) is t
    now[0] += 55  # 605 s in all: past the longest a session lives
    assert sessions.get(t.token) is None
    u = sessions.open(Person("bob", Role.viewer, "web"))
    sessions.close(u.token)
    assert sessions.get(u.token) is None and sessions.get("no such token") is None


def test_the_lockout_counts_names_and_addresses_and_ends(monkeypatch: Any) -> None:
    now = [0.0]
    monkeypatch.setattr(time, "monotonic", lambda: now[0])
    lock = Lockout(after=3, lock=30)
    for _ in range(2):
        lock.failed("ann", "10.0.0.1")
    assert lock.locked_for("ann", "10.0.0.1") == 0
    lock.failed("ann", "10.0.0.2")
    assert lock.locked_for("ann", "10.0.0.9") == 30  # the name, from anywhere
    assert lock.locked_for("bob", "10.0.0.9") == 0
    for _ in range(3):
        lock.failed(f"u{_}", "10.0.0.7")
    assert lock.locked_for("carol", "10.0.0.7") == 30  # the address, whatever name
    now[0] += 31
    assert lock.locked_for("ann", "10.0.0.9") == 0
    lock.succeeded("ann")
    lock.failed("ann", "10.0.0.9")
    assert lock.locked_for("ann", "10.0.0.9") == 0  # a success starts the name's count again


def test_a_timeline_merges_like_states_folds_slivers_and_keeps_the_state_now() -> None:
    from datetime import UTC, datetime, timedelta

    from gwc.record.store import Segment
    from gwc.web import record

    t0 = datetime(2026, 11, 28, tzinfo=UTC)
    segs, t = [], t0
    for i in range(2 * record.TIMELINE_MAX):  # alternating states, each a sliver of the day but the first
        width = timedelta(hours=1) if i == 0 else timedelta(seconds=1)
        segs.append(Segment(t, t + width, "Idle" if i % 2 else "Running", "run", "standby" if i % 2 else "productive"))
        t += width
    segs.append(Segment(t, t + timedelta(seconds=1), "Idle", "start", "standby"))  # merges with the one before
    segs.append(
        Segment(t + timedelta(seconds=1), t + timedelta(seconds=2), "Shutdown", "operator_stop", "non_scheduled")
    )
    out = record._segments(segs, t0, t0 + timedelta(days=1))
    assert len(out) <= record.TIMELINE_MAX
    assert out[0]["e10"] == "productive" and out[-1]["e10"] == "non_scheduled"  # the state now is kept
    assert sum(s["seconds"] for s in out) == sum(s.seconds for s in segs)  # nothing lost, only folded
    short = record._segments(segs[:3], t0, t0 + timedelta(days=1))
    assert [s["e10"] for s in short] == ["productive", "standby", "productive"]
