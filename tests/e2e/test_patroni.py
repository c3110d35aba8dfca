"""A replicated cell database under Patroni with etcd (issue 36), on network-namespace hosts.

h1, h2, h3 each run an etcd member and a Patroni member (Debian's packages; PostgreSQL 15,
synchronous replication on); h4 runs the cell, whose database URL names the three members with
`target_session_attrs=read-write`, so every connection finds the primary. While lots run: a planned
switchover (`gwc db switchover`), then the primary's host killed whole (every process in it, and its
cable): Patroni promotes the synchronous standby, the modules reconnect to it, every lot is exported,
no committed row is lost and `gwc check` is clean.

A long walk (about three minutes): `bin/test -m soak tests/e2e/test_patroni.py`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc.config import dump_toml
from gwc.netns import Hosts, leftovers, unavailable
from gwc.patroni import primary_url
from gwc.soak.private_config import private_bus
from tests.harness import SERVERS, wait_for

MISSING = next((p for p in ("patroni", "etcd") if shutil.which(p) is None), None)
BIN = next(iter(sorted(Path("/usr/lib/postgresql").glob("*/bin"))), None)

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.soak,
    pytest.mark.skipif(unavailable() is not None, reason=f"{unavailable()}"),
    pytest.mark.skipif(MISSING is not None, reason=f"{MISSING} is not installed (bin/setup installs it)"),
]

MEMBERS = ("h1", "h2", "h3")
PASSWORD = "patroni-test"


class PatroniCluster:
    """etcd and Patroni on h1..h3: started, killed with their hosts, and the hosts' removal ends them."""

    # Failover within about ttl + loop_wait of the primary's death (loop_wait + 2 * retry_timeout must
    # stay under ttl: Patroni's rule against a leader that cannot renew in time).
    DCS: dict[str, float] = {"ttl": 6, "loop_wait": 1, "retry_timeout": 2}
    ETCD_TIMING = ("--heartbeat-interval", "100", "--election-timeout", "1000")  # ms

    def __init__(self, hosts: Hosts, base: Path) -> None:
        self.hosts = hosts
        self.base = base
        self.addr = {h: hosts[h].address for h in MEMBERS}
        self.procs: list[subprocess.Popen[bytes]] = []

    def _spawn(self, host: str, argv: list[str], log: str) -> None:
        with open(self.base / host / log, "wb") as out:
            self.procs.append(subprocess.Popen(self.hosts[host].argv(argv), stdout=out, stderr=subprocess.STDOUT))

    def start(self) -> None:
        initial = ",".join(f"{h}=http://{a}:2380" for h, a in self.addr.items())
        for h, a in self.addr.items():
            (self.base / h).mkdir(parents=True)
            self._spawn(h, [
                "etcd", "--name", h, "--data-dir", str(self.base / h / "etcd"),
                "--listen-client-urls", f"http://{a}:2379", "--advertise-client-urls", f"http://{a}:2379",
                "--listen-peer-urls", f"http://{a}:2380", "--initial-advertise-peer-urls", f"http://{a}:2380",
                "--initial-cluster", initial, "--initial-cluster-state", "new",
                *self.ETCD_TIMING,
                "--logger", "zap",  # timestamps to the millisecond, for a failover's timeline
            ], "etcd.log")  # fmt: skip
        for h in MEMBERS:  # Patroni's etcd client gives up at once on a cluster whose version is not decided
            wait_for(lambda h=h: self.etcd_ready(h), 60, f"etcd on {h}", interval=0.2)
        for h in MEMBERS:
            self._patroni(h)
            if h == "h1":  # the first bootstraps the cluster; the others clone it
                wait_for(lambda: self.roles().get("h1") == "leader", 60, "h1 to bootstrap the cluster", interval=0.5)
        wait_for(lambda: self.streaming() == 2, 90, "two replicas streaming", interval=0.5)

    def _patroni(self, h: str) -> None:
        a = self.addr[h]
        pg = self.base / h / "pg"
        pg.mkdir()
        shutil.chown(pg, "postgres", "postgres")
        pg.chmod(0o700)
        subnet = a.rsplit(".", 1)[0] + ".0/24"
        doc = {
            "scope": "gwc",
            "name": h,
            "restapi": {"listen": f"{a}:8008", "connect_address": f"{a}:8008"},
            "etcd3": self.etcd3(h),
            "bootstrap": {
                "dcs": {
                    **self.DCS,
                    "synchronous_mode": True,  # a commit waits for the sync standby: it survives the primary
                    "postgresql": {"use_pg_rewind": True, "parameters": {"fsync": "off"}},
                },
                "initdb": [{"encoding": "UTF8"}],
                "pg_hba": [
                    "local all all trust",
                    f"host replication replicator {subnet} scram-sha-256",
                    f"host all all {subnet} scram-sha-256",
                ],
            },
            "postgresql": {
                "listen": f"{a}:5432",
                "connect_address": f"{a}:5432",
                "data_dir": str(pg / "data"),
                "bin_dir": str(BIN),
                "pgpass": str(pg / "pgpass"),
                "authentication": {
                    "superuser": {"username": "postgres", "password": PASSWORD},
                    "replication": {"username": "replicator", "password": PASSWORD},
                },
                "parameters": {"unix_socket_directories": str(pg), "max_connections": 200},
            },
        }
        conf = self.base / h / "patroni.yml"
        conf.write_text(json.dumps(doc))  # YAML is a superset of JSON
        conf.chmod(0o644)
        self._spawn(h, ["runuser", "-u", "postgres", "--", "patroni", str(conf)], "patroni.log")

    def etcd_ready(self, h: str) -> bool:
        """Whether h's etcd member serves a cluster that has decided its version (it has a quorum)."""
        argv = ["curl", "-s", "-m", "2", f"http://{self.addr[h]}:2379/version"]
        r = subprocess.run(self.hosts[h].argv(argv), capture_output=True, text=True)
        try:
            return json.loads(r.stdout).get("etcdcluster", "not_decided") != "not_decided"
        except ValueError:
            return False

    def etcd3(self, h: str) -> dict[str, Any]:
        """Patroni's etcd3 section on host h: its own host's member first, the others after, taken in this
        order (`use_proxies`: no discovery). Left to discover, Patroni talks to a member picked at random
        from etcd's member list and keeps it while it answers: a standby whose member died with the
        primary's host first waits out its etcd client's timeout (retry_timeout / 2 per member) and has its
        watch restarted. Its own host's member dies only with it."""
        own = [self.addr[h], *(a for x, a in self.addr.items() if x != h)]
        return {"hosts": [f"{a}:2379" for a in own], "use_proxies": True}

    def cluster(self) -> list[dict[str, Any]]:
        for h in MEMBERS:
            r = subprocess.run(
                self.hosts[h].argv(["curl", "-s", "-m", "2", f"http://{self.addr[h]}:8008/cluster"]),
                capture_output=True,
                text=True,
            )
            try:
                return list(json.loads(r.stdout)["members"])
            except (ValueError, KeyError):
                continue
        return []

    def roles(self) -> dict[str, str]:
        return {m["name"]: m["role"] for m in self.cluster()}

    def leader(self) -> str | None:
        return next((n for n, r in self.roles().items() if r == "leader"), None)

    def streaming(self) -> int:
        return sum(1 for m in self.cluster() if m["role"] != "leader" and m["state"] in ("streaming", "running"))

    def url(self) -> str:
        return primary_url("postgres", PASSWORD, [(a, 5432) for a in self.addr.values()], "gwc")

    def kill_host(self, host: str) -> None:
        pids = subprocess.run(["ip", "netns", "pids", self.hosts[host].netns], capture_output=True, text=True)
        for pid in pids.stdout.split():
            try:
                os.kill(int(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.hosts.cut(host)


class CellOnH4:
    """A one-host cell on h4 (no [[host]] tables: every module there) using the cluster."""

    def __init__(self, hosts: Hosts, base: Path, cluster: PatroniCluster) -> None:
        self.host = hosts["h4"]
        self.var = base / "h4"
        self.cluster = cluster
        machines = [
            {"id": "cmm_wc", "kind": "cmm", "serial": {"port": "sim", "timeout": 5.0},
             "sim": {"measure_time": 0.2, "pattern": "P"}},
            {"id": "wc1", "kind": "dummy", "run_time": 1.0},
            {"id": "wc2", "kind": "dummy", "run_time": 1.0},
        ]  # fmt: skip
        # A module reconnecting after the failover tries the members in turn, on its event loop: a dead
        # member's connect_timeout (2 s) is a pause in its heartbeats. Liveness above it, or the Machine
        # Server shuts down the machines of WCs that were only reconnecting (docs/deploying.md, 3).
        for m in machines:
            m["liveness"] = 6.0
        doc = {
            "cell": {"name": "patroni", "var": str(self.var)},
            "bus": private_bus(peer_timeout=1.5, heartbeat=0.2),
            "database": {
                "url": cluster.url(),
                "patroni": [f"http://{a}:8008" for a in cluster.addr.values()],
            },
            "log": {"level": "note"},
            "module": [{"name": m} for m in SERVERS],
            "machine": machines,
        }
        (self.var / "etc").mkdir(parents=True)
        (self.var / "etc" / "cell.toml").write_text(dump_toml(doc))

    def run(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        env = {
            "PATH": "/usr/sbin:/usr/bin:/sbin:/bin",
            "GWC_CONFIG": str(self.var / "etc" / "cell.toml"),
            "GWC_VAR": str(self.var),
            "PYTHONUNBUFFERED": "1",
        }
        argv = self.host.argv([sys.executable, "-m", "gwc", *args])
        return subprocess.run(argv, env=env, capture_output=True, text=True, timeout=timeout)

    def gwc(self, *args: str, timeout: float = 120) -> str:
        r = self.run(*args, timeout=timeout)
        assert r.returncode == 0, f"gwc {' '.join(args)}: exit {r.returncode}: {r.stderr}{r.stdout}"
        return r.stdout

    def sql(self, text: str) -> list[list[Any]]:
        """A query on the primary, from h4 (the test itself is not on the bridge)."""
        code = (
            "import json, sys, psycopg\n"
            "with psycopg.connect(sys.argv[1], autocommit=True) as c:\n"
            "    cur = c.execute(sys.argv[2])\n"
            "    print(json.dumps(cur.fetchall() if cur.description else [], default=str))\n"
        )
        url = self.cluster.url().replace("/gwc?", "/{db}?")
        db = "postgres" if text.lower().startswith("create database") else "gwc"
        r = subprocess.run(
            self.host.argv([sys.executable, "-c", code, url.format(db=db), text]), capture_output=True, text=True
        )
        assert r.returncode == 0, r.stderr
        return list(json.loads(r.stdout))

    def start_machine(self, machine: str) -> None:
        t = threading.Thread(target=lambda: self.gwc("machine", "start", machine))
        t.start()
        while t.is_alive():
            for (no,) in self.sql(
                "select alarm_no from alarms where cleared_at is null and machine_id = "
                f"'{machine}' and alarm_id = 'HOME_CMM'"
            ):
                self.gwc("alarm", "clear", str(no))
            t.join(0.3)

    def last_binding(self) -> int:
        return int(
            self.sql(
                "select greatest((select max(machine_run_id) from reserved_machines), "
                "(select max(machine_run_id) from machine_run_outcome), 0)"
            )[0][0]
        )

    def lots_done(self, entities: list[int]) -> bool:
        ids = ",".join(map(str, entities))
        states = dict(self.sql(f"select entity_id, state from lot_status where entity_id in ({ids})"))
        failed = [e for e, s in states.items() if s == "failed"]
        assert not failed, self.sql("select entity_id, reason from lot_status where state = 'failed'")
        if "waiting_import" in states.values():
            self.gwc("import", "--all")
        if "waiting_export" in states.values():
            self.gwc("export", "--all")
        return len(states) == len(entities) and set(states.values()) == {"exported"}


@pytest.fixture
def patroni_cell() -> Iterator[tuple[PatroniCluster, CellOnH4]]:
    base = Path(tempfile.mkdtemp(prefix="gwc-p-", dir="/var/tmp"))
    base.chmod(0o755)
    try:
        with Hosts(4) as hosts:
            tag = hosts.tag
            cluster = PatroniCluster(hosts, base)
            cell = None
            try:
                cluster.start()
                cell = CellOnH4(hosts, base, cluster)
                yield cluster, cell
            finally:
                if cell is not None:
                    cell.run("stop", timeout=90)
                for p in cluster.procs:
                    p.kill()
    finally:
        shutil.rmtree(base, ignore_errors=True)
    assert not leftovers(tag), "test hosts left behind"


def test_lots_ride_out_a_switchover_and_the_primary_host_killed(patroni_cell: Any) -> None:
    cluster, cell = patroni_cell
    cell.sql("create database gwc")
    cell.gwc("db", "init")
    cell.gwc("start", timeout=240)
    for m in ("cmm_wc", "wc1", "wc2"):
        cell.start_machine(m)
    listed = json.loads(cell.gwc("db", "cluster", "--json"))
    assert sorted(m["role"] for m in listed)[0] == "leader" and len(listed) == 3, listed
    assert any(m["role"] == "sync_standby" for m in listed), listed

    made = json.loads(cell.gwc("order", "new", "--customer", "NJIT", "milled_pawn=6", "--json"))
    entities = [e for lot in made["lots"] for e in lot["entities"]]
    running = "select 1 from machine_status where status = 'Running'"
    wait_for(lambda: cell.lots_done(entities) or cell.sql(running), 60, "a run", interval=0.3)

    # A planned switchover while lots run.
    first = cluster.leader()
    cell.gwc("db", "switchover")
    wait_for(lambda: cluster.leader() not in (None, first), 60, "a new leader after the switchover", interval=0.5)
    wait_for(lambda: cluster.streaming() == 2, 90, "both replicas streaming again", interval=0.5)
    # Until Patroni has confirmed a synchronous standby of the new primary, it promotes nobody if that
    # primary dies (synchronous_mode: only a confirmed sync standby may): kill it only after.
    sync = lambda: any(m["role"] == "sync_standby" for m in cluster.cluster())
    wait_for(sync, 60, "a synchronous standby of the new primary", interval=0.5)

    # The primary's host killed whole while lots run: Patroni promotes the synchronous standby.
    wait_for(lambda: cell.lots_done(entities) or cell.sql(running), 60, "a run", interval=0.3)
    counts = "select (select count(*) from lot_status), (select count(*) from machine_run_outcome)"
    committed = cell.sql(counts)[0]
    victim = cluster.leader()
    assert victim is not None
    before = cell.last_binding()
    cluster.kill_host(victim)
    killed = time.monotonic()
    wait_for(lambda: cluster.leader() not in (None, victim), 90, "the sync standby promoted", interval=0.2)
    promoted = time.monotonic() - killed
    bound = lambda: cell.lots_done(entities) or cell.last_binding() > before
    wait_for(bound, 90, "the next machine bound", interval=0.2)
    resumed = time.monotonic() - killed
    wait_for(lambda: cell.lots_done(entities), 180, "every lot exported", interval=0.5)
    now = cell.sql(counts)[0]
    assert now[0] == committed[0] and now[1] >= committed[1], (committed, now)  # no committed row lost
    milled = cell.sql("select count(*) from machine_run_outcome where machine_id <> 'cmm_wc' and ack_code = 'ACK_OK'")
    assert milled[0][0] == 6, milled
    check = cell.run("check")
    assert check.returncode == 0, check.stdout + check.stderr
    print(f"switchover from {first}; {victim} killed: new leader after {promoted:.1f}s, next binding {resumed:.1f}s")


def sql_on(hosts: Hosts, host: str, url: str, text: str) -> list[list[Any]]:
    """A query through `url`, run on a test host (the test itself is not on the bridge)."""
    code = (
        "import json, sys, psycopg\n"
        "with psycopg.connect(sys.argv[1], autocommit=True) as c:\n"
        "    cur = c.execute(sys.argv[2])\n"
        "    print(json.dumps(cur.fetchall() if cur.description else [], default=str))\n"
    )
    r = subprocess.run(hosts[host].argv([sys.executable, "-c", code, url, text]), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return list(json.loads(r.stdout))


def test_the_host_of_the_active_servers_and_the_primary_killed_while_lots_run() -> None:
    """The issue's topology: h1 the active servers and the database primary, h2 their standbys and the
    synchronous standby, h3 the machines and a replica, etcd on all three. h1 killed whole while lots
    run (their scripts ordered on h2): Patroni promotes h2, h2's standbys take every lease, every lot
    is exported, nothing is milled twice and `gwc check` is clean."""
    with issue_topology(PatroniCluster, "gwc-p-") as (hosts, cluster, cell, url):
        walk_h1_killed(hosts, cluster, cell, url)


@contextlib.contextmanager
def issue_topology(
    make_cluster: Callable[[Hosts, Path], PatroniCluster], prefix: str, extra: dict[str, Any] | None = None
) -> Iterator[tuple[Hosts, PatroniCluster, Any, str]]:
    """Issue 36's three hosts: Patroni (`make_cluster`) and etcd on all three, the cell's servers active
    on h1 with standbys on h2, the machines on h3; each host's cell.toml written with `extra` sections.
    Yields (hosts, cluster, cell, the multi-host URL); stops the cell host by host and the cluster, and
    checks no test host is left. GWC_TEST_KEEP=DIR keeps the hosts' folders for a post-mortem."""
    from tests.e2e.test_hosts import HostCell

    base = Path(tempfile.mkdtemp(prefix=prefix, dir="/var/tmp"))
    base.chmod(0o755)
    try:
        with Hosts(3) as hosts:
            tag = hosts.tag
            # Apart from the cell's var/ folders, which the cell makes private (root's): the members
            # run as the postgres user.
            (base / "patroni").mkdir()
            cluster = make_cluster(hosts, base / "patroni")
            cell: HostCell | None = None
            try:
                cluster.start()
                url = cluster.url()
                sql_on(hosts, "h3", url.replace("/gwc?", "/postgres?"), "create database gwc")
                cell = HostCell(hosts, base)
                doc = cell.doc
                doc["database"] = {"url": url, "patroni": [f"http://{a}:8008" for a in cluster.addr.values()]}
                doc["module"] = [{"name": m, "host": "h1", "standby": ["h2"]} for m in SERVERS]
                doc["machine"] = [
                    {**m, "host": "h3", "liveness": 6.0} for m in doc["machine"] if m["id"] in ("cmm_wc", "wc1", "wc2")
                ]
                doc["lease"] = {"ttl": 3.0}
                doc.update(extra or {})
                for h in MEMBERS:
                    cell.config_path(h).write_text(
                        dump_toml({**doc, "cell": {"name": "hosts", "var": str(cell.var(h))}})
                    )
                yield hosts, cluster, cell, url
            finally:
                if cell is not None:
                    for h in ("h3", "h2", "h1"):
                        try:
                            cell.run(h, "stop", timeout=60)
                        except subprocess.TimeoutExpired:
                            pass
                for p in cluster.procs:
                    p.kill()
    finally:
        if keep := os.environ.get("GWC_TEST_KEEP"):
            shutil.copytree(base, keep, dirs_exist_ok=True, symlinks=True, ignore=shutil.ignore_patterns(".s.PGSQL*"))
        shutil.rmtree(base, ignore_errors=True)
    assert not leftovers(tag), "test hosts left behind"


def start_on_hosts(cell: Any, q: Callable[[str], list[list[Any]]]) -> None:
    """`gwc start` host by host in issue_topology's cell (h1 first: the schema, the cell key and the
    active servers; var/secrets/ copied; h2's standbys; h3's machines), then every machine started."""
    cell.gwc("h1", "start", timeout=240)
    cell.copy_secrets()
    cell.gwc("h2", "start", timeout=240)
    cell.gwc("h3", "start", timeout=240)
    for m in ("cmm_wc", "wc1", "wc2"):
        machine_start(cell, q, m)


def machine_start(cell: Any, q: Callable[[str], list[list[Any]]], machine: str) -> None:
    """`gwc machine start` on h3, pushing the CMM's start button (its HOME_CMM alarm cleared) when it asks."""
    t = threading.Thread(target=lambda: cell.gwc("h3", "machine", "start", machine))
    t.start()
    while t.is_alive():
        for (no,) in q(f"select alarm_no from alarms where cleared_at is null and machine_id = '{machine}' "
                       "and alarm_id = 'HOME_CMM'"):  # fmt: skip
            cell.gwc("h3", "alarm", "clear", str(no))
        t.join(0.3)


def lots_exported(cell: Any, q: Callable[[str], list[list[Any]]], entities: list[int]) -> bool:
    """Every one of `entities` exported (importing and exporting from h2 as they ask); none failed."""
    ids = ",".join(map(str, entities))
    states = dict(q(f"select entity_id, state from lot_status where entity_id in ({ids})"))
    assert "failed" not in states.values(), q("select entity_id, reason from lot_status where state = 'failed'")
    if "waiting_import" in states.values():
        cell.gwc("h2", "import", "--all")
    if "waiting_export" in states.values():
        cell.gwc("h2", "export", "--all")
    return len(states) == len(entities) and set(states.values()) == {"exported"}


def newest_binding(q: Callable[[str], list[list[Any]]]) -> int:
    """The newest machine_run_id bound (reserved now, or its run ended)."""
    return int(q("select greatest((select max(machine_run_id) from reserved_machines), "
                 "(select max(machine_run_id) from machine_run_outcome), 0)")[0][0])  # fmt: skip


def walk_h1_killed(hosts: Hosts, cluster: PatroniCluster, cell: Any, url: str) -> None:
    def q(text: str) -> list[list[Any]]:
        return sql_on(hosts, "h3", url, text)

    start_on_hosts(cell, q)
    assert cluster.leader() == "h1"
    assert {h for (h,) in q("select host from module_leases")} == {"h1"}
    made = json.loads(cell.gwc("h2", "order", "new", "--customer", "NJIT", "milled_pawn=4", "--json"))
    entities = [e for lot in made["lots"] for e in lot["entities"]]

    def done() -> bool:
        return lots_exported(cell, q, entities)

    def last_binding() -> int:
        return newest_binding(q)

    wait_for(lambda: done() or q("select 1 from machine_status where status = 'Running'"), 90, "a run", interval=0.3)
    counts = "select (select count(*) from lot_status), (select count(*) from machine_run_outcome)"
    committed = q(counts)[0]
    before = last_binding()
    cluster.kill_host("h1")
    killed = time.monotonic()
    wait_for(lambda: cluster.leader() not in (None, "h1"), 60, "a new primary", interval=0.2)
    promoted = time.monotonic() - killed
    wait_for(lambda: done() or last_binding() > before, 60, "the next machine bound", interval=0.2)
    resumed = time.monotonic() - killed
    wait_for(lambda: {h for (h,) in q("select host from module_leases")} == {"h2"}, 60, "h2 holding every lease")
    wait_for(done, 180, "every lot exported", interval=0.5)
    now = q(counts)[0]
    assert now[0] == committed[0] and now[1] >= committed[1], (committed, now)
    milled = q("select count(*) from machine_run_outcome where machine_id <> 'cmm_wc' and ack_code = 'ACK_OK'")
    assert milled[0][0] == 4, milled
    check = cell.run("h2", "check")
    assert check.returncode == 0, check.stdout + check.stderr
    print(f"h1 killed: new primary after {promoted:.1f}s, next machine bound after {resumed:.1f}s")
