"""Lot scripts outlive their host (issue 36): which host runs each script, and its record in the database.

On one host a killed lot script is restarted by that host's agent and resumes its entity from its
traveller (var/lots/entity-E.json, gwc/lot/resume.py). In a cell over several hosts that file dies
with its host, so there (`hosted`) each script also saves its traveller into LOT_TRAVELLERS, and
every host's agent beats once a second (`beat`, sql/092_lot_hosts.sql): it renews its host in
LOT_HOSTS and names the scripts it runs or queues (LOT_SCRIPT_HOSTS). A host whose beat is older than
`ttl`, and whose agent the claiming agent does not hear on the bus, is dead to the cell (after a
database outage every host's beat is stale; the bus tells the live ones): the first live agent to
beat claims its unfinished entities and starts their scripts, which resume from LOT_TRAVELLERS
exactly as a script killed with -9 does.

Fencing: a host thought dead may only be cut off. Its scripts cannot save once another host holds
their entities (`lot_traveller_save` refuses: the script exits at once, 75, without touching what
the new script holds), and its agent, beating again once the link is back, is told which of its
scripts were taken (`lost`) and kills them without a restart.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc.cell import pid_file
from gwc.config import Config
from gwc.errors import GwcError

DEFAULT_TTL_S = 4.0  # s: a host whose agent has not beaten for this long is dead to the cell
BEAT_S = 1.0  # s: how often an agent beats
EXIT_TAKEN_OVER = 75  # a script whose entity another host's agent took over (not restarted: it removed its pid file)


def hosted(cfg: Config) -> bool:
    """Whether lot scripts outlive their host: a cell over several hosts, unless `[lot_hosts] enabled
    = false`. A one-host cell keeps its travellers on its disk alone, as before."""
    return len(cfg.hosts) > 1 and bool(cfg.raw.get("lot_hosts", {}).get("enabled", True)) and cfg.host is not None


def ttl(cfg: Config) -> float:
    """[lot_hosts] ttl: how long a silent host's scripts are left to it."""
    value = float(cfg.raw.get("lot_hosts", {}).get("ttl", DEFAULT_TTL_S))
    if not 1.0 <= value <= 600.0:
        raise ValueError(f"[lot_hosts] ttl must be 1..600 s, got {value}")
    return value


@dataclass(frozen=True)
class Beat:
    """An agent's beat's answer: entities whose scripts it must start now, and ones it must stop."""

    take: list[int]
    lost: list[int]


def beat(conn: psycopg.Connection[Any], host: str, ttl_s: float, mine: list[int], room: int, heard: list[str]) -> Beat:
    """One beat, one transaction (see the module docstring). `heard`: the hosts whose agents this one hears
    on the bus, alive whatever their beats say."""
    rows = conn.execute(
        "select what, entity_id from lot_hosts_beat(%s, %s::real, %s::bigint[], %s, %s::text[])",
        (host, ttl_s, mine, room, heard),
    ).fetchall()
    conn.commit()
    return Beat([int(e) for w, e in rows if w == "take"], [int(e) for w, e in rows if w == "lost"])


async def beat_async(
    conn: psycopg.AsyncConnection[Any], host: str, ttl_s: float, mine: list[int], room: int, heard: list[str]
) -> Beat:
    """`beat` on an autocommit connection of an event loop (the agent's: it runs no thread)."""
    cur = await conn.execute(
        "select what, entity_id from lot_hosts_beat(%s, %s::real, %s::bigint[], %s, %s::text[])",
        (host, ttl_s, mine, room, heard),
    )
    rows = await cur.fetchall()
    return Beat([int(e) for w, e in rows if w == "take"], [int(e) for w, e in rows if w == "lost"])


async def others_async(conn: psycopg.AsyncConnection[Any], host: str, per_host: int) -> dict[str, list[int]]:
    """Up to `per_host` of the entities each other host's agent runs or queues the scripts of, lowest
    first: what this host's agent may start ahead should that host fall silent (gwc/agent/lot_hosts.py)."""
    cur = await conn.execute(
        "select host, entity_id from (select host, entity_id, row_number() over (partition by host order by "
        "entity_id) as n from lot_script_hosts where host <> %s) s where n <= %s order by host, entity_id",
        (host, per_host),
    )
    others: dict[str, list[int]] = {}
    for h, e in await cur.fetchall():
        others.setdefault(str(h), []).append(int(e))
    return others


class TravellerStore:
    """A lot script's traveller in LOT_TRAVELLERS (hosted cells): saved beside the file, read back by the
    script that takes the entity over. `reads` is the entity's LotReads (its query asks again while the
    database is away)."""

    def __init__(self, cfg: Config, entity_id: int, reads: Any, log: logging.Logger) -> None:
        self.cfg = cfg
        self.entity_id = entity_id
        self.reads = reads
        self.log = log
        self.unreachable: str | None = None  # why the database cannot be reached by this script, once known

    def save(self, traveller: dict[str, Any]) -> None:
        if self.unreachable is not None:
            return
        doc = json.dumps(traveller, default=str)
        try:
            rows = self.reads.query(
                "select lot_traveller_save(%s, %s, %s, %s::jsonb)", self.entity_id, self.cfg.host, os.getpid(), doc
            )
        except (GwcError, OSError) as e:
            self._unreachable(e)
            return
        if rows and rows[0][0] is False:
            self.taken_over()

    def _unreachable(self, e: BaseException) -> None:
        """The script cannot reach the database at all (on a host other than the embedded database's, a
        lot user without var/secrets/lot.database): its record stays on its host's disk, and the script
        does not outlive its host (docs/deploying.md)."""
        self.unreachable = str(e)
        self.log.error(
            "entity %d: its traveller cannot be kept in the database (%s): this script will not outlive its host",
            self.entity_id,
            e,
        )

    def read(self) -> dict[str, Any] | None:
        try:
            row = self.reads.query_one("select traveller from lot_travellers where entity_id = %s", self.entity_id)
        except (GwcError, OSError) as e:
            self._unreachable(e)
            return None
        if row is None:
            return None
        doc = row[0]
        return dict(doc) if isinstance(doc, dict) else dict(json.loads(doc))

    def taken_over(self) -> None:
        """Another host runs this entity's script now: stop at once and touch nothing (the new script
        holds the entity's requests and machines; a cleanup here would take them from it)."""
        self.log.error(
            "entity %d: another host's agent took this lot script over (this host was thought dead): exiting",
            self.entity_id,
        )
        with contextlib.suppress(OSError):
            pid_file(self.cfg, f"lot:{self.entity_id}").unlink()  # its agent does not restart it
        for h in logging.getLogger().handlers + self.log.handlers:
            with contextlib.suppress(Exception):
                h.flush()
        os._exit(EXIT_TAKEN_OVER)


__all__ = ["BEAT_S", "EXIT_TAKEN_OVER", "Beat", "TravellerStore", "beat", "beat_async", "hosted", "others_async", "ttl"]
