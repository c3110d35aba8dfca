"""The module lease (gwc/lease.py, sql/080_redundancy.sql) on a real database: one active instance,
takeover when the holder's session goes or its lease expires, and fencing: nothing a deposed holder
writes lands once another took over."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.cell import cell_procs
from gwc.config import Config
from gwc.errors import ConfigError, DatabaseUnavailable
from gwc.lease import Claim, Deposed, Lease, LeaseSettings
from gwc.soak.private_config import write_config

LOG = logging.getLogger("test.lease")
TTL = 1.0


def instance(host: str) -> Lease:
    return Lease("msched", LeaseSettings(ttl=TTL, poll=0.05), LOG, host)


def connect(cfg: Config) -> psycopg.Connection[Any]:
    return db.connect(cfg, role="msched", log=LOG, attempts=1)


def until_taken(lease: Lease, conn: psycopg.Connection[Any], within: float = 10.0) -> Claim:
    """A standby's tries, as its poll makes them, until it holds the lease."""
    deadline = time.monotonic() + within
    while True:
        claim = lease.claim(conn)
        if claim.held_by_me or time.monotonic() > deadline:
            return claim
        time.sleep(0.05)


def takeovers(conn: psycopg.Connection[Any]) -> list[tuple[str, int, str]]:
    conn.rollback()
    rows = conn.execute("select how, epoch, host from lease_takeovers where name = 'msched' order by 1, 2").fetchall()
    conn.rollback()
    return sorted(rows)


def test_one_instance_holds_the_lease_and_a_standby_takes_it_when_its_session_ends(
    cell_config: Config, db_conn: psycopg.Connection[Any]
) -> None:
    a, b = instance("h1"), instance("h2")
    ca, cb = connect(cell_config), connect(cell_config)
    try:
        assert a.claim(ca).how == "first" and a.active and a.epoch == 1
        held = b.claim(cb)
        assert (held.how, held.epoch, held.holder) == ("held", 1, a.holder) and not b.active
        assert a.claim(ca).how == "again"  # a reconnect of the holder keeps its epoch
        ca.close()  # the holder dies: PostgreSQL frees its lock with its session (the backend exits soon after)
        took = until_taken(b, cb)
        assert (took.how, took.epoch) == ("free", 2) and b.active
        assert takeovers(db_conn) == [("first", 1, "h1"), ("free", 2, "h2")]
    finally:
        ca.close()
        cb.close()


def test_an_expired_holder_is_fenced_and_nothing_it_writes_afterwards_lands(
    cell_config: Config, db_conn: psycopg.Connection[Any]
) -> None:
    a, b = instance("h1"), instance("h2")
    ca, cb = connect(cell_config), connect(cell_config)
    try:
        a.claim(ca)
        cur = ca.cursor()
        a.renew(cur)
        ca.commit()
        assert b.claim(cb).how == "held"  # renewed: not taken, however often asked
        # The holder stalls (cut off, or stopped) with its session open: after the ttl a standby's
        # try terminates that session, and its next try takes the lease.
        time.sleep(TTL + 0.2)
        took = until_taken(b, cb)
        assert (took.how, took.epoch) == ("expired", 2)
        # The deposed holder's writes fail: its session is gone ...
        with pytest.raises(psycopg.OperationalError):
            ca.execute("insert into accept_types (machine_id, op_type) select machine_id, 'mill' from me_config")
            ca.commit()
        # ... and a new connection of it cannot take the lease back: it learns it was deposed.
        again = connect(cell_config)
        try:
            with pytest.raises(Deposed, match="took the lease over"):
                a.claim(again)
            assert not a.active
        finally:
            again.close()
        assert db_conn.execute("select count(*) from accept_types where op_type = 'mill'").fetchone() == (0,)
        # The new holder renews; the old one's renewal (were it to get a session) is refused.
        b.renew(cb.cursor())
        cb.commit()
    finally:
        ca.close()
        cb.close()


def test_after_a_database_failover_a_fresh_lease_waits_for_its_holder(
    cell_config: Config, db_conn: psycopg.Connection[Any]
) -> None:
    """On a new primary no session holds the lock; a lease renewed on the old server is its holder's
    until it expires, so that a holder that is only reconnecting is not deposed."""
    a, b = instance("h1"), instance("h2")
    ca, cb = connect(cell_config), connect(cell_config)
    try:
        a.claim(ca)
        ca.close()
        db_conn.execute("update module_leases set server = server - interval '1 hour' where name = 'msched'")
        db_conn.commit()
        assert b.claim(cb).how == "held"
        again = connect(cell_config)
        try:
            assert a.claim(again).how == "again" and a.active  # the holder, reconnected, keeps it
        finally:
            again.close()
    finally:
        ca.close()
        cb.close()


def test_a_renewal_on_a_lost_session_is_a_database_error_not_a_silent_success(cell_config: Config) -> None:
    a = instance("h1")
    ca = connect(cell_config)
    a.claim(ca)
    ca.close()
    with pytest.raises((psycopg.Error, DatabaseUnavailable)):
        a.renew(ca.cursor())


def test_a_standby_host_runs_the_module_too_and_both_instances_are_leased(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    doc: dict[str, Any] = {
        "cell": {"name": "t", "var": str(tmp_path / "var")},
        "host": [{"name": "h1", "address": "127.0.0.1"}, {"name": "h2", "address": "198.51.100.7"}],
        "database": {"host": "h1"},
        "module": [{"name": "msched", "host": "h1", "standby": ["h2"]}, {"name": "ms", "host": "h1"}],
    }
    monkeypatch.setenv("GWC_HOST", "h2")
    cfg = write_config(tmp_path / "etc" / "cell.toml", doc)
    assert [p.name for p in cell_procs(cfg)] == ["msched"]  # the standby; ms runs on h1 only
    assert cfg.leased("msched") and not cfg.leased("ms")
    monkeypatch.setenv("GWC_HOST", "h1")
    assert [p.name for p in cell_procs(write_config(tmp_path / "etc" / "cell.toml", doc))] == ["msched", "ms"]
    doc["module"][0]["standby"] = ["h9"]
    with pytest.raises(ConfigError, match="standby"):
        write_config(tmp_path / "etc" / "cell.toml", doc)


def test_a_one_host_cell_has_no_lease_unless_asked(tmp_path: Path) -> None:
    doc: dict[str, Any] = {"cell": {"name": "t", "var": str(tmp_path / "var")}, "module": [{"name": "msched"}]}
    cfg = write_config(tmp_path / "etc" / "cell.toml", doc)
    assert Lease.of(cfg, "msched", LOG) is None
    doc["module"][0]["lease"] = True
    lease = Lease.of(write_config(tmp_path / "etc" / "cell.toml", doc), "msched", LOG)
    assert lease is not None and (lease.settings.ttl, lease.settings.deadline) == (3.0, 2.0)
