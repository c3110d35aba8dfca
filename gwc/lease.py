"""Which instance of a redundant module is the active one: a lease in the database (issue 36).

A singleton module (MSCHED, the servers, the OPC UA gateway) may run as one active instance and
standbys on other hosts ([[module]] standby = ["h2"] in cell.toml). The database decides, never the
bus: each instance tries `lease_claim()` (sql/080_redundancy.sql) on the connection it will work
through. The winner holds a session advisory lock there and a row in MODULE_LEASES with a new epoch;
the others stand by, off the bus, trying again every `poll` seconds.

Fencing, so that nothing a deposed instance does lands after a standby took over:

- in the database: the active does every write through the session that holds the lock. A standby
  takes the lease only when that session is gone (the holder died: PostgreSQL freed the lock at
  once) or after `lease_fence()` terminated it (the lease was not renewed for `ttl`: a holder cut
  off or stalled with its connection still open). A reconnecting holder must claim again with its
  epoch, which fails once another took over (`Deposed`).
- on the bus: a standby is not on the bus. The active renews its lease every ttl/4; if it could
  not for `deadline` (2/3 of the ttl, before any standby may fence it) it deposes itself: it stops
  serving, leaves the bus and exits with EXIT_DEPOSED, and its agent starts it again, a standby.

The new active signs on under the module's name (a new incarnation, as a restarted module) and
carries on from the tables exactly as a module restarted after kill -9 does.
"""

from __future__ import annotations

import asyncio
import logging
import os
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc.config import Config
from gwc.errors import DatabaseError, DatabaseUnavailable, GwcError

# The exit code of an instance that lost its lease: its agent starts it again at once, as a standby,
# and does not count it a failed start.
EXIT_DEPOSED = 75
DEFAULT_TTL_S = 3.0
DEFAULT_POLL_S = 0.25


class Deposed(DatabaseUnavailable):
    """This instance no longer holds its module's lease: another took over. It must stop serving."""


@dataclass(frozen=True)
class LeaseSettings:
    """[lease] in cell.toml: `ttl` (s) a lease lives unrenewed; `poll` (s) between a standby's tries."""

    ttl: float = DEFAULT_TTL_S
    poll: float = DEFAULT_POLL_S

    @classmethod
    def of(cls, cfg: Config) -> LeaseSettings:
        raw = cfg.raw.get("lease", {})
        ttl, poll = float(raw.get("ttl", DEFAULT_TTL_S)), float(raw.get("poll", DEFAULT_POLL_S))
        if not 0.5 <= ttl <= 600 or not 0.01 <= poll <= ttl / 2:
            raise GwcError(f"[lease] ttl must be 0.5..600 s and poll 0.01..ttl/2 s (got ttl {ttl}, poll {poll})")
        return cls(ttl, poll)

    @property
    def renew_every(self) -> float:
        return self.ttl / 4

    @property
    def deadline(self) -> float:
        """How long the holder goes on without a renewal before it deposes itself: well before the
        `ttl` after which a standby may fence it (the two clocks differ only in their start)."""
        return self.ttl * 2 / 3


@dataclass(frozen=True)
class Claim:
    """lease_claim()'s answer: the lease's epoch and holder, and how this try went."""

    epoch: int
    holder: str
    how: str  # first, free, expired, again (this instance holds it); held, deposed (it does not)

    @property
    def held_by_me(self) -> bool:
        return self.how in ("first", "free", "expired", "again")


class Lease:
    """One instance's side of its module's lease. All calls are on the module's own connection."""

    def __init__(self, name: str, settings: LeaseSettings, log: logging.Logger, host: str | None) -> None:
        self.name = name
        self.settings = settings
        self.log = log
        self.host = host
        self.holder = f"{host or 'local'}:{os.getpid()}:{secrets.token_hex(3)}"
        self.epoch = 0  # 0: not (yet) active
        self.renewed = 0.0  # monotonic time of the last renewal that succeeded (sent at)
        self.lost: str | None = None  # why this instance was deposed, once it was

    @classmethod
    def of(cls, cfg: Config, name: str, log: logging.Logger) -> Lease | None:
        """The module's lease, if cell.toml runs it with one (else None: the one-host default)."""
        return cls(name, LeaseSettings.of(cfg), log, cfg.host) if cfg.leased(name) else None

    @property
    def active(self) -> bool:
        return self.epoch > 0 and self.lost is None

    def claim(self, conn: psycopg.Connection[Any]) -> Claim:
        """One try (one transaction). Raises Deposed if this instance was active and is no more."""
        sent = time.monotonic()
        try:
            row = conn.execute(
                "select epoch, holder, how from lease_claim(%s, %s, %s, %s::real, %s::bigint)",
                (self.name, self.holder, self.host, self.settings.ttl, self.epoch),
            ).fetchone()
            conn.commit()
        except psycopg.OperationalError as e:
            raise DatabaseUnavailable(f"lease of {self.name}: {e}") from e
        except psycopg.Error as e:
            conn.rollback()
            raise DatabaseError(f"lease of {self.name}: {e}") from e
        assert row is not None
        claim = Claim(int(row[0]), str(row[1]), str(row[2]))
        if claim.how == "deposed":
            self._depose(f"{claim.holder} took the lease over (epoch {claim.epoch})")
        if claim.held_by_me:
            if claim.how != "again":
                self.log.warning("active: took the lease of %s (%s, epoch %d)", self.name, claim.how, claim.epoch)
            self.epoch, self.renewed = claim.epoch, sent
        return claim

    def renew(self, cur: psycopg.Cursor[Any]) -> None:
        """Prove the holder alive, in the caller's transaction on the locked session (Module's step,
        which retries and reconnects); Deposed when the lease is not this instance's any more."""
        sent = time.monotonic()
        row = cur.execute("select lease_renew(%s, %s, %s::bigint)", (self.name, self.holder, self.epoch)).fetchone()
        if not row or not row[0]:
            self._depose(f"the lease of {self.name} (epoch {self.epoch}) is not ours any more")
        self.renewed = sent

    def due(self) -> bool:
        """Whether a renewal is due."""
        return time.monotonic() - self.renewed >= self.settings.renew_every

    def overdue(self) -> bool:
        """Whether the holder went `deadline` without a renewal: it must depose itself, for a standby
        may fence it soon."""
        return time.monotonic() - self.renewed >= self.settings.deadline

    def _depose(self, why: str) -> None:
        self.lost = self.lost or why
        raise Deposed(f"deposed: {why}")

    def depose(self, why: str) -> None:
        """Give the lease up from this side (overdue): Deposed."""
        self._depose(why)

    async def wait(self, connect: Callable[[], psycopg.Connection[Any]], ready: Callable[[], None]) -> Any:
        """Stand by until this instance holds the lease; return the connection that holds it.

        `connect` makes a connection (DatabaseError when it cannot); `ready` is called once, when the
        instance stands by (or is active at once): the agent's proof that it is up."""
        conn: psycopg.Connection[Any] | None = None
        said: str | None = None
        told = False
        while True:
            try:
                if conn is None or conn.closed:
                    conn = await asyncio.to_thread(connect)
                claim = self.claim(conn)
                if claim.held_by_me:
                    return conn
                if said != claim.holder:
                    said = claim.holder
                    self.log.warning("standby: %s is active (epoch %d)", claim.holder, claim.epoch)
            except DatabaseError as e:
                if conn is not None:
                    conn.close()
                conn = None
                if said != str(e):
                    said = str(e)
                    self.log.warning("standby: cannot reach the lease (%s): trying again", e)
            if not told:
                told = True
                ready()
            await asyncio.sleep(self.settings.poll)
