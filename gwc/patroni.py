"""A replicated cell database under Patroni (issue 36): what the cell knows of such a cluster.

The cell does not run Patroni: the plant (or tests/e2e/test_patroni.py) runs PostgreSQL under
Patroni with etcd as its consensus store, one member per host, synchronous replication on. The
cell is given a multi-host URL whose libpq option `target_session_attrs=read-write` makes every
connection find the primary, whichever member it is now (`primary_url`), and in cell.toml the
members' REST addresses, so that `gwc db cluster` shows who leads and `gwc db switchover` hands
the primary over:

    [database]
    url = "postgresql://gwc:...@10.20.0.1:5432,10.20.0.2:5432,10.20.0.3:5432/gwc?target_session_attrs=read-write"
    patroni = ["http://10.20.0.1:8008", "http://10.20.0.2:8008", "http://10.20.0.3:8008"]
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from dataclasses import dataclass
from typing import Any

from gwc.config import Config
from gwc.errors import ConfigError, DatabaseError

TIMEOUT_S = 3.0


@dataclass(frozen=True)
class Member:
    """One member of the Patroni cluster, as its REST API's /cluster tells."""

    name: str
    role: str  # leader, sync_standby, replica
    state: str  # running, streaming, starting, stopped, ...
    host: str
    port: int
    timeline: int | None
    lag: int | None  # bytes behind the leader (None for the leader, or unknown)


def rest_urls(cfg: Config) -> list[str]:
    """[database] patroni: the members' REST addresses (ConfigError when the cell has none)."""
    urls = cfg.raw.get("database", {}).get("patroni") or []
    if not isinstance(urls, list) or not urls:
        raise ConfigError("[database] patroni names no member (a list of http://HOST:8008 addresses)")
    return [str(u).rstrip("/") for u in urls]


def primary_url(user: str, password: str, members: list[tuple[str, int]], dbname: str = "gwc") -> str:
    """A libpq URL that reaches whichever member is the primary (read-write) now."""
    hosts = ",".join(f"{h}:{p}" for h, p in members)
    return f"postgresql://{user}:{password}@{hosts}/{dbname}?target_session_attrs=read-write&connect_timeout=2"


def _call(url: str, method: str = "GET", body: dict[str, Any] | None = None) -> Any:
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=TIMEOUT_S) as r:
        text = r.read().decode()
    try:
        return json.loads(text)
    except ValueError:
        return text


def members(cfg: Config) -> list[Member]:
    """The cluster as the first member that answers sees it; DatabaseError when none does."""
    errors = []
    for base in rest_urls(cfg):
        try:
            doc = _call(f"{base}/cluster")
        except (OSError, urllib.error.URLError) as e:
            errors.append(f"{base}: {e}")
            continue
        return [
            Member(
                m["name"],
                m["role"],
                m["state"],
                m["host"],
                int(m["port"]),
                m.get("timeline"),
                m.get("lag") if isinstance(m.get("lag"), int) else None,
            )
            for m in doc.get("members", [])
        ]
    raise DatabaseError("no Patroni member answered: " + "; ".join(errors))


def switchover(cfg: Config, to: str | None = None) -> str:
    """Hand the primary over (to member `to`, or the sync standby): Patroni's planned switchover."""
    now = members(cfg)
    leader = next((m.name for m in now if m.role == "leader"), None)
    if leader is None:
        raise DatabaseError("the cluster has no leader now: nothing to hand over (a failover is under way?)")
    body: dict[str, Any] = {"leader": leader}
    if to:
        body["candidate"] = to
    errors = []
    for base in rest_urls(cfg):
        try:
            return str(_call(f"{base}/switchover", "POST", body))
        except urllib.error.HTTPError as e:
            raise DatabaseError(f"switchover refused: {e.code} {e.read().decode(errors='replace')}") from e
        except (OSError, urllib.error.URLError) as e:
            errors.append(f"{base}: {e}")
    raise DatabaseError("no Patroni member answered: " + "; ".join(errors))
