"""Lot scripts outlive their host, and production resumes within 10 s of losing h1 (issue 36).

The issue's topology on network-namespace hosts (gwc/netns.py): h1 the active servers and MSCHED and
the Patroni primary, h2 their standbys and the synchronous standby, h3 the machines and a replica,
etcd on all three. Six pawns are ordered, three from h1 (their lot scripts run on h1) and three from h2.
h1 is killed whole (every process in it, its cable cut) while they run, etcd's leader moved to h1
first (the worst case): Patroni promotes its synchronous standby (h2 or h3), h2's standbys take every
lease, a live host's agent takes h1's lot scripts over (sql/092_lot_hosts.sql: started ahead while the
database failed over, gwc/agent/lot_hosts.py) and they resume their entities from LOT_TRAVELLERS, as a
script killed with -9 does. Every lot is exported, nothing is milled twice, no committed row is lost,
`gwc check` is clean, and production resumes (the next machine bound, read from the new MSCHED's log)
within the issue's 10 s of the kill; the failover's steps, read from the hosts' logs, are printed.

About 1.5 minutes: `.venv/bin/python -m pytest -q -s -m soak tests/e2e/test_lot_hosts.py`
(GWC_TEST_ETCD_LEADER=none leaves etcd's leader where it is; GWC_TEST_DCS="ttl,loop_wait,retry_timeout"
and GWC_TEST_ETCD="heartbeat,election" try other timings).
"""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from gwc.netns import Hosts, unavailable
from gwc.patroni import primary_url
from tests.e2e.test_patroni import (
    MEMBERS,
    MISSING,
    PASSWORD,
    PatroniCluster,
    issue_topology,
    lots_exported,
    newest_binding,
    sql_on,
    start_on_hosts,
)
from tests.harness import wait_for

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.soak,
    pytest.mark.skipif(unavailable() is not None, reason=f"{unavailable()}"),
    pytest.mark.skipif(MISSING is not None, reason=f"{MISSING} is not installed (bin/setup installs it)"),
]

BAR_S = 10.0  # the issue's bar from the kill to production going on (its goal: 3 s), held in the worst case
# the test builds: etcd's leader dies with h1, and h1's lots may hold every machine, so that production
# waits for their scripts to resume on a live host (docs/reliability.md has the trials).
LOT_HOSTS_TTL = 4.0


class QuickPatroni(PatroniCluster):
    """Patroni's and etcd's timing (GWC_TEST_DCS="ttl,loop_wait,retry_timeout" and
    GWC_TEST_ETCD="heartbeat,election" in ms to try others). Patroni takes the three as whole seconds
    (it int()s them: a loop_wait of 0.5 is 0, a loop that never sleeps); its rule against a leader that
    cannot renew in time: loop_wait + 2 x retry_timeout <= ttl."""

    ETCD_TIMING = tuple(
        x
        for flag, ms in zip(
            ("--heartbeat-interval", "--election-timeout"), os.environ.get("GWC_TEST_ETCD", "50,250").split(",")
        )
        for x in (flag, ms)
    )
    DCS = {
        k: int(v)
        for k, v in zip(("ttl", "loop_wait", "retry_timeout"), os.environ.get("GWC_TEST_DCS", "5,1,2").split(","))
    }


def test_h1_killed_with_servers_primary_and_lot_scripts_they_resume_elsewhere_and_production_goes_on() -> None:
    extra = {"lot_hosts": {"ttl": LOT_HOSTS_TTL}}
    with issue_topology(QuickPatroni, "gwc-lh-", extra) as (hosts, cluster, cell, url):
        walk(hosts, cluster, cell, url)


def etcd_call(hosts: Hosts, cluster: PatroniCluster, host: str, path: str, body: dict[str, Any]) -> Any:
    """A call of etcd's v3 JSON gateway on `host`'s member (from h3: the test is not on the bridge)."""
    url = f"http://{cluster.addr[host]}:2379/v3/{path}"
    argv = ["curl", "-s", "-m", "3", "-X", "POST", url, "-d", json.dumps(body)]
    r = subprocess.run(hosts["h3"].argv(argv), capture_output=True, text=True)
    return json.loads(r.stdout or "{}")


def etcd_leader_to(hosts: Hosts, cluster: PatroniCluster, host: str) -> None:
    """Make `host`'s etcd member the leader: the worst case for a failover when that host dies (etcd
    elects a leader first, and extends every lease, Patroni's leader key among them, by its election
    timeout)."""
    ids = {m["name"]: m["ID"] for m in etcd_call(hosts, cluster, "h3", "cluster/member/list", {})["members"]}
    names = {i: n for n, i in ids.items()}

    def leader() -> str | None:
        return names.get(str(etcd_call(hosts, cluster, "h3", "maintenance/status", {}).get("leader")))

    now = leader()
    if now != host and now is not None:
        etcd_call(hosts, cluster, now, "maintenance/transfer-leadership", {"targetID": ids[host]})
    wait_for(lambda: leader() == host, 20, f"etcd's leader on {host}", interval=0.2)


def first_binding_after(log: Path, since: float) -> float | None:
    """When the first machine was bound after `since` (wall clock), from MSCHED's log: the cell's own
    clock, not the test's polling through a subprocess."""
    for line in log.read_text(errors="replace").splitlines():
        if " bound: entity " not in line or "| Date " not in line:
            continue
        stamp = line.split("| Date ", 1)[1].split(" |", 1)[0]
        at = datetime.datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S.%f").timestamp()
        if at > since:
            return at
    return None


def stamps(log: Path, needle: str, since: float) -> list[float]:
    """When lines holding `needle` were written after `since` (wall clock): the cell's Figure 2 logs
    ("| Date Y-m-d H:M:S.f |"), Patroni's and PostgreSQL's ("Y-m-d H:M:S,f" / ".f" first), etcd's zap
    JSON ("ts":"...Z")."""
    found = []
    for line in log.read_text(errors="replace").splitlines() if log.exists() else []:
        if needle not in line:
            continue
        if "| Date " in line:
            at = datetime.datetime.strptime(line.split("| Date ", 1)[1][:23], "%Y-%m-%d %H:%M:%S.%f").timestamp()
        elif '"ts":"' in line:
            iso = line.split('"ts":"', 1)[1].split('"', 1)[0].replace("Z", "+00:00")
            at = datetime.datetime.fromisoformat(iso).timestamp()
        else:
            try:
                at = datetime.datetime.strptime(line[:23].replace(",", "."), "%Y-%m-%d %H:%M:%S.%f").timestamp()
            except ValueError:
                continue
        if at > since:
            found.append(at)
    return found


def timeline(cluster: PatroniCluster, cell: Any, entities: list[int], wall: float) -> list[tuple[str, float | None]]:
    """A failover's steps read from the hosts' logs, in seconds after the kill (None: not seen)."""
    pat = cluster.base

    def first(*found: list[float]) -> float | None:
        every = [t for f in found for t in f]
        return min(every) - wall if every else None

    def last(*found: list[float]) -> float | None:
        every = [t for f in found for t in f]
        return max(every) - wall if every else None

    logs = [cell.var(h) / "log" for h in ("h2", "h3")]
    new = next((h for h in ("h2", "h3") if stamps(pat / h / "patroni.log", "promoted self to leader", wall)), "h2")
    patroni = pat / new / "patroni.log"
    rest = first(stamps(patroni, "Request failed to h1", wall))
    return [
        ("etcd's new leader", first(*(stamps(pat / h / "etcd.log", "elected leader", wall) for h in ("h2", "h3")))),
        (f"{new}'s Patroni asks h1's REST API (leader key gone)", None if rest is None else rest - 2.0),
        ("... and gives up on it (2 s)", rest),
        (f"{new} promoted (leader lock)", first(stamps(patroni, "promoted self to leader", wall))),
        (f"{new} accepts connections", first(stamps(patroni, "ready to accept connections", wall))),
        ("first lease taken", first(*(stamps(f, "active: took the lease", wall) for f in logs[0].glob("*.log")))),
        ("MSCHED's lease", first(stamps(logs[0] / "msched.log", "active: took the lease", wall))),
        ("last lease taken", last(*(stamps(f, "active: took the lease", wall) for f in logs[0].glob("*.log")))),
        ("a WC back on the database", first(*(stamps(f, "database is back", wall) for f in logs[1].glob("wc-*.log")))),
        (
            "h1's scripts claimed",
            first(*(stamps(d / f"agent-{d.parent.name}.log", "taking over the scripts", wall) for d in logs)),
        ),
        (
            "first of them started",
            first(*(stamps(d / f"lot-{e}.log", "lot script process for entity", wall) for d in logs for e in entities)),
        ),
        (
            "last of them started",
            last(*(stamps(d / f"lot-{e}.log", "lot script process for entity", wall) for d in logs for e in entities)),
        ),
        ("next machine bound", first(stamps(logs[0] / "msched.log", " bound: entity ", wall))),
        (
            "etcd elections in the walk",
            float(sum(len(stamps(pat / h / "etcd.log", "became leader", 0)) for h in MEMBERS)),
        ),
    ]


def walk(hosts: Hosts, cluster: PatroniCluster, cell: Any, url: str) -> None:
    live_url = url  # after the kill: the members but h1, so that the test's own reads do not wait for it

    def q(text: str) -> list[list[Any]]:
        deadline = time.monotonic() + 30
        while True:  # the members may all be read-only for a moment: Patroni names its leader, then promotes
            try:
                return sql_on(hosts, "h3", live_url, text)
            except AssertionError as e:
                if "read-only" not in str(e) or time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    start_on_hosts(cell, q)
    assert cluster.leader() == "h1"
    assert {h for (h,) in q("select host from module_leases")} == {"h1"}
    if os.environ.get("GWC_TEST_ETCD_LEADER", "h1") == "h1":
        etcd_leader_to(hosts, cluster, "h1")  # the worst case: the consensus store loses its leader too
    entities: dict[str, list[int]] = {}
    for h in ("h1", "h2"):  # each host's agent runs the scripts of its order
        made = json.loads(cell.gwc(h, "order", "new", "--customer", "NJIT", "milled_pawn=3", "--json"))
        entities[h] = [e for lot in made["lots"] for e in lot["entities"]]
    every = entities["h1"] + entities["h2"]
    ids = ",".join(map(str, every))
    on_h1 = ",".join(map(str, entities["h1"]))
    wait_for(
        lambda: (
            {int(e) for (e,) in q(f"select entity_id from lot_script_hosts where entity_id in ({ids})")} == set(every)
        ),
        30,
        "every script's host recorded",
    )

    def done() -> bool:
        return lots_exported(cell, q, every)

    def last_binding() -> int:
        return newest_binding(q)

    counts = "select (select count(*) from lot_status), (select count(*) from machine_run_outcome)"
    # The moment to kill h1, read in one query so that the kill follows at once (a query here is a process
    # started in a test host: a second under load, in which h1's lots may finish): a run going on, lots
    # waiting for machines, an operation of h1's scripts recorded and at least two of them with work left.
    moment = (
        f"select (select count(*) from lot_travellers where entity_id in ({on_h1}) "
        "and jsonb_array_length(coalesce(traveller->'operations', '[]')) > 0) > 0 "
        "and exists (select 1 from machine_status where status = 'Running') "
        "and exists (select 1 from request_machines), "
        f"(select coalesce(array_agg(entity_id), '{{}}') from lot_status where entity_id in ({on_h1}) "
        "and state not in ('exported', 'failed', 'completed', 'waiting_export')), "
        "greatest((select max(machine_run_id) from reserved_machines), "
        "(select max(machine_run_id) from machine_run_outcome), 0), "
        "(select count(*) from lot_status), (select count(*) from machine_run_outcome)"
    )

    def ready() -> list[Any] | None:
        busy, work, binding, lots, outcomes = q(moment)[0]
        return [list(work), int(binding), [lots, outcomes]] if busy and len(work) >= 2 else None

    found = wait_for(lambda: done() or ready(), 120, "a run, a queue, and two of h1's scripts at work", interval=0.3)
    assert isinstance(found, list), "every lot finished before the moment to kill h1 came"
    at_work, before, committed = found  # h1's entities with work left: their scripts die with h1
    wall = time.time()
    cluster.kill_host("h1")
    killed = time.monotonic()
    live_url = primary_url("postgres", PASSWORD, [(cluster.addr[h], 5432) for h in ("h2", "h3")], "gwc")
    wait_for(lambda: cluster.leader() not in (None, "h1"), 60, "a new primary", interval=0.1)
    promoted = time.monotonic() - killed
    wait_for(lambda: done() or last_binding() > before, 60, "the next machine bound", interval=0.1)
    polled = time.monotonic() - killed
    wait_for(
        lambda: (
            not q(f"select 1 from lot_script_hosts where entity_id in ({on_h1}) and host = 'h1'")
            or not q(f"select 1 from lot_status where entity_id in ({on_h1}) and state not in ('exported', 'failed')")
        ),
        60,
        "h1's lot scripts taken over",
        interval=0.2,
    )
    taken = time.monotonic() - killed
    wait_for(lambda: {h for (h,) in q("select host from module_leases")} == {"h2"}, 60, "h2 holding every lease")
    wait_for(done, 240, "every lot exported", interval=0.5)
    now = q(counts)[0]
    assert now[0] == committed[0] and now[1] >= committed[1], (committed, now)
    milled = q("select count(*) from machine_run_outcome where machine_id <> 'cmm_wc' and ack_code = 'ACK_OK'")
    assert milled[0][0] == 6, milled  # nothing milled twice, every pawn milled
    moved = q(f"select entity_id, host from lot_travellers where entity_id in ({','.join(map(str, at_work))})")
    assert len(moved) == len(at_work) and all(h != "h1" for _, h in moved), moved  # resumed and finished on a live host
    check = cell.run("h2", "check")
    assert check.returncode == 0, check.stdout + check.stderr
    bound = first_binding_after(cell.var("h2") / "log" / "msched.log", wall)
    assert bound is not None, "h2's MSCHED bound nothing after the kill"
    resumed = bound - wall
    print(
        f"h1 killed at {datetime.datetime.fromtimestamp(wall):%H:%M:%S.%f} (Patroni {cluster.DCS}, etcd "
        f"{' '.join(cluster.ETCD_TIMING)}): new primary after {promoted:.1f}s, next machine bound after "
        f"{resumed:.2f}s (seen by the test after {polled:.1f}s), h1's lot scripts taken over after {taken:.1f}s"
    )
    for what, at in timeline(cluster, cell, entities["h1"], wall):
        print(f"  {'-' if at is None else f'{at:6.2f}'}  {what}")
    print(f"the issue's bar ({BAR_S:g}s): {'met' if resumed < BAR_S else 'NOT met'}")
    assert resumed < BAR_S, f"production resumed {resumed:.1f}s after the kill (the issue's bar: {BAR_S:g}s)"
