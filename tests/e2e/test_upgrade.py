"""A rolling upgrade while lots run (issue 36, item 4): the cell moved module by module to a second
build whose wire version is one higher (with one new optional message field) and whose schema version
is one higher (with one additive migration). No lot fails, nothing is run twice, `gwc check` is clean,
and the Conversation Monitor shows modules of both versions talking, each to the other in the older.

The second build is real: this checkout's gwc/, sql/ and pyproject.toml copied to a folder and patched
there; a process runs it with PYTHONPATH naming that folder (and started in it).

* The default suite's test (one host, about 30 s): MSCHED and the Lot Server, each with a standby of
  the new build started by hand, handed over while 2 lots run; a module of the new build started
  before the migration refuses the old schema.
* The soak test walks docs/deploying.md, 7 on the issue's network-namespace hosts (gwc/netns.py,
  tests/e2e/test_patroni.py's issue_topology: h1 the active servers and MSCHED, h2 their standbys, h3
  the machines, the database under Patroni on all three) while lots are ordered without pause: the
  schema from h2; h2's agent and standbys on the new build; h1's agent on it and `gwc upgrade
  handover`; h3's agent, then its machines one by one (`gwc machine stop`, `gwc restart me:M wc:M`,
  `gwc machine start`). "Installing" the build on a host is killing its agent (-9: the modules run
  on) and `gwc start` from the new build, whose agent adopts them. About 3 minutes:
  `.venv/bin/python -m pytest -q -s -m soak tests/e2e/test_upgrade.py` (as root)."""

from __future__ import annotations

import collections
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from gwc.config import PROJECT_ROOT
from gwc.ipc import wire
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.netns import Host, unavailable
from gwc.schema import SCHEMA_VERSION
from tests.e2e.lotkit import cell_with_machines, gwc, import_export_all, ok, order, stop_lot_scripts, wait_state
from tests.e2e.test_patroni import MISSING, PatroniCluster, issue_topology, machine_start, sql_on, start_on_hosts
from tests.e2e.test_redundancy import LEASED, Standbys, gone, holder, leased_cell, no_run_twice, standing_by
from tests.harness import SERVERS, CellHarness, wait_for
from tests.leaks import MARK

pytestmark = pytest.mark.e2e

NEW_WIRE = wire.VERSION + 1
NEW_SCHEMA = SCHEMA_VERSION + 1
AGENT_RESTART_S = 15.0  # [lot_hosts] ttl in the walk on hosts: above what an agent's restart takes here


def patch(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) == 1, f"{path.name}: the upgrade test's patch no longer applies at {old!r}"
    path.write_text(text.replace(old, new))


def second_build(where: Path) -> Path:
    """This build, copied and patched: wire VERSION + 1 (reading this one's too), one new optional field
    (Startup_Ack's `build`, which the new build sends), schema version + 1 by an additive migration."""
    root = where / "build2"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "node_modules")
    shutil.copytree(PROJECT_ROOT / "gwc", root / "gwc", ignore=ignore)
    shutil.copytree(PROJECT_ROOT / "sql", root / "sql")
    shutil.copy(PROJECT_ROOT / "pyproject.toml", root / "pyproject.toml")  # (gwc.config.from_checkout)
    patch(
        root / "gwc" / "ipc" / "wire.py",
        f"VERSION = {wire.VERSION}\nMIN_VERSION = {wire.MIN_VERSION}\n",
        f"VERSION = {NEW_WIRE}\nMIN_VERSION = {wire.VERSION}\n",
    )
    patch(
        root / "gwc" / "ipc" / "catalogue.py",
        '_msg("Startup_Ack", "startup accepted (ACK_OK) or refused (Notnow, Start_Fail)", **ACK),',
        f'_msg("Startup_Ack", "startup accepted or refused", build="str?@{NEW_WIRE}", **ACK),',
    )
    patch(root / "gwc" / "module.py", 'note=f"{m.name} is already started")', 'note="already", build="2")')
    patch(root / "gwc" / "schema.py", f"SCHEMA_VERSION = {SCHEMA_VERSION}\n", f"SCHEMA_VERSION = {NEW_SCHEMA}\n")
    (root / "sql" / "096_upgrade_test.sql").write_text(
        "alter table lot_status add column if not exists upgrade_note text;\n"
        f"select schema_version_reached({NEW_SCHEMA}, {SCHEMA_VERSION}, 'lot_status.upgrade_note');\n"
    )
    return root


def new_env(cell: CellHarness, build: Path) -> dict[str, str]:
    return {**cell.env(), "PYTHONPATH": str(build)}


def run_new(cell: CellHarness, build: Path, *args: str, timeout: float = 60) -> str:
    result = subprocess.run(  # in the build's folder: `python -m` puts the working folder first on the path
        [sys.executable, "-m", "gwc", *args],
        env=new_env(cell, build),
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=build,
    )
    return ok(result)


@pytest.fixture
def upgrade_cell(xprocess: Any, tmp_path_factory: pytest.TempPathFactory, pg_cluster: Any) -> Iterator[Any]:
    import uuid

    from psycopg import sql

    name = f"gwc_t_{uuid.uuid4().hex[:12]}"
    with pg_cluster.admin() as conn:
        conn.execute(
            sql.SQL("create database {} template {}").format(sql.Identifier(name), sql.Identifier(pg_cluster.template))
        )
    cell = leased_cell(lambda **c: CellHarness(xprocess, tmp_path_factory.mktemp("upgrade"), pg_cluster.url(name), **c))
    new = Standbys(cell)
    try:
        cell_with_machines(cell, "wc1", "wc2", "cmm_wc")
        yield cell, new, second_build(tmp_path_factory.mktemp("build"))
    finally:
        stop_lot_scripts(cell)
        cell.close()
        new.close()
        with pg_cluster.admin() as conn:
            conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))


def start_standby(standbys: Standbys, name: str, build: Path | None) -> subprocess.Popen[bytes]:
    """A standby of this build (None) or of the second, started as an agent would."""
    if build is None:
        return standbys.start(name)
    cell = standbys.cell
    out = open(cell.cfg.log_dir / f"standby-{name}-new-{len(standbys.procs)}.out", "wb")  # noqa: SIM115
    env = {k: v for k, v in new_env(cell, build).items() if k != MARK}
    p = subprocess.Popen(
        [sys.executable, "-m", "gwc", "run", name],
        env=env,
        stdout=out,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=build,
    )
    out.close()
    standbys.procs.append(p)
    standbys.names[p.pid] = name
    return p


def test_msched_and_the_lot_server_handed_over_to_a_new_build_while_lots_run(upgrade_cell: Any, tmp_path: Path) -> None:
    """While 2 lots run: a module of the new build refuses the old schema; the schema migrated; h2's
    standbys started on the new build; h1's active instances handed over to them."""
    cell, new, build = upgrade_cell
    record = tmp_path / "monitor.jsonl"
    monitor = start_monitor(cell.env(), record)
    try:
        # A module of the new build refuses the schema before the migration, saying what to do.
        early = start_standby(new, "msched", build)
        assert early.wait(30) == 3
        assert "apply this build's schema first" in cell.log_text("msched")
        entities = order(cell, "milled_pawn=2")  # lots of the old build
        for e in entities:
            wait_state(cell, e, "waiting_import")
        ok(gwc(cell, "import", "--all"))
        wait_for(
            lambda: cell.query("select count(*) from machine_status where status in ('Setup', 'Running')")[0][0] > 0,
            30,
            "a machine at work",
        )
        began = time.time()
        # 1. The schema, with the new build, while everything runs: additive, so the old build runs on.
        run_new(cell, build, "db", "init")
        assert cell.query("select version, compatible_from from schema_version") == [(NEW_SCHEMA, SCHEMA_VERSION)]
        # 2. h2: standbys of the new build (standing by: nothing is interrupted).
        said = {name: cell.log_text(name).count("standby: ") for name in LEASED}
        for name in LEASED:
            start_standby(new, name, build)
        for name in LEASED:
            wait_for(lambda name=name: standing_by(cell, name, said[name] + 1), 20, f"a new {name} standby")
        # 3. h1: the active instances handed over, standby first, while the lots run.
        epochs = {name: holder(cell, name)[0] for name in LEASED}
        handed = run_new(cell, build, "upgrade", "handover", *LEASED)
        for name in LEASED:
            assert f"{name}: handed over" in handed and holder(cell, name)[0] == epochs[name] + 1
            assert f"it speaks wire version {NEW_WIRE}" in handed, handed
        status = run_new(cell, build, "upgrade", "status", "--listen", "0.5")
        assert f"database: schema {NEW_SCHEMA}, runs builds of schema {SCHEMA_VERSION}..{NEW_SCHEMA}" in status
        new_line = next(line for line in status.splitlines() if line.startswith(f"wire {NEW_WIRE}: "))
        assert "ls" in new_line and "msched" in new_line and "wc:wc1" not in new_line, status
        assert f"the cell speaks wire version {wire.VERSION}" in status, status
        # A field the new build added is left out for the old: an old receiver would drop it as unknown.
        conv, answer = cell.bus.request("STARTUP", message("Startup_Request", module="msched"), to="msched")
        conv.end()
        assert answer.first.ack_code == AckCode.NOTNOW and "build" not in answer.first.fields
        import_export_all(cell, entities, timeout=120)
        ended = time.time()
        no_run_twice(cell, entities)
        run_new(cell, build, "check")
    finally:
        stop_monitor(monitor)
    mixed = between_versions(talk(record, began, ended))
    print(f"monitor: {len(mixed)} messages between versions during the upgrade")


def start_monitor(env: dict[str, str], record: Path, cwd: Path | None = None, host: Host | None = None) -> Any:
    """`gwc monitor --json --members --record RECORD` (on `host`, from the build in `cwd`), once it listens."""
    argv = [sys.executable, "-m", "gwc", "monitor", "--json", "--members", "--record", str(record), "--duration", "900"]
    monitor = subprocess.Popen(
        host.argv(argv) if host else argv,
        env=env,
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert monitor.stderr is not None and "monitoring bus" in monitor.stderr.readline()
    return monitor


def stop_monitor(monitor: Any) -> None:
    monitor.terminate()
    monitor.wait(10)


@dataclass(frozen=True)
class Said:
    """One message the monitor recorded, with the wire version its sender and its addressee speak."""

    at: float
    sender: str
    from_speaks: int
    to: str
    to_speaks: int
    wire: int


def talk(record: Path, began: float, ended: float) -> list[Said]:
    """The monitor's record: the messages sent from [began, ended] to one module, each with the wire
    version its sender and its addressee spoke then (it changes as a module is upgraded)."""
    from datetime import datetime

    speaks: dict[str, int] = {}
    said: list[Said] = []
    for line in record.read_text().splitlines():
        r = json.loads(line)
        if "member" in r:
            speaks[r["member"]] = r["speaks"]
        if "message" not in r:
            continue
        if r.get("speaks"):
            speaks[r["from"]] = r["speaks"]
        at = datetime.fromisoformat(r["time"]).timestamp()
        theirs = speaks.get(r["to"] or "")
        if began <= at <= ended and r.get("speaks") and theirs:
            said.append(Said(at, r["from"], r["speaks"], r["to"], theirs, r["wire"]))
    return said


def between_versions(said: list[Said]) -> list[Said]:
    """The messages from a module of one version to one of the other: both ways, every one in the
    older version (a newer module speaks the older one to it)."""
    mixed = [m for m in said if m.from_speaks != m.to_speaks]
    assert {(m.from_speaks, m.to_speaks) for m in mixed} >= {(NEW_WIRE, wire.VERSION), (wire.VERSION, NEW_WIRE)}
    assert {m.wire for m in mixed} == {wire.VERSION}, [m for m in mixed if m.wire != wire.VERSION][:5]
    return mixed


def wires(record: Path) -> list[tuple[float, int]]:
    """(when, wire version) of every message the monitor recorded."""
    from datetime import datetime

    recs = [json.loads(line) for line in record.read_text().splitlines()]
    return [(datetime.fromisoformat(r["time"]).timestamp(), r["wire"]) for r in recs if "message" in r]


# ------------------------------------------------------------- the walk on network-namespace hosts


@pytest.mark.soak
@pytest.mark.timeout(900)  # about 3 minutes on the shared 2-core machine
@pytest.mark.skipif(unavailable() is not None, reason=f"{unavailable()}")
@pytest.mark.skipif(MISSING is not None, reason=f"{MISSING} is not installed (bin/setup installs it)")
def test_a_rolling_upgrade_host_by_host_while_lots_run_loses_no_lot_and_both_versions_talk() -> None:
    """The issue's hosts (tests/e2e/test_patroni.py's issue_topology): h1 the active servers and MSCHED,
    h2 their standbys, h3 the machines, the database under Patroni on all three. While lots run, the
    new build replaces the old host by host as docs/deploying.md, 7 says: the schema from h2, h2's
    standbys, h1's actives handed over to them, h3's machines one by one; at the end the cell moves up
    to the new wire version by itself."""
    # An agent restarted on the new build beats again within seconds; a host silent for [lot_hosts] ttl
    # has its lot scripts taken over (they resume elsewhere): the ttl stays above what a restart takes.
    extra = {"lot_hosts": {"ttl": AGENT_RESTART_S}}
    with issue_topology(PatroniCluster, "gwc-up-", extra) as (hosts, _cluster, cell, url):
        walk_hosts(hosts, cell, url, second_build(cell.base))


class Operator:
    """The plant while the cell is upgraded: orders coming in from `orders_from` (hosts not being upgraded
    at the time, in turn) whenever fewer than `keep` entities are at work, and the operator on h2
    importing and exporting every lot that waits for it, until stopped. Remembers the host each entity
    was ordered on and the build its script runs (its agent's, the build installed there then)."""

    def __init__(self, cell: Any, q: Any, orders_from: tuple[str, ...], keep: int = 4) -> None:
        self.cell, self.q = cell, q
        self.orders_from = orders_from
        self.keep = keep
        self.entities: dict[int, tuple[str, str]] = {}  # entity -> (host, "old" or "new" build)
        self._turn = 0
        self.errors: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def order(self, host: str, items: str) -> None:
        made = json.loads(self.cell.gwc(host, "order", "new", "--customer", "NJIT", items, "--json"))
        build = "new" if host in self.cell.builds else "old"
        with self._lock:
            for lot in made["lots"]:
                self.entities.update(dict.fromkeys(lot["entities"], (host, build)))

    def states(self) -> dict[int, str]:
        with self._lock:
            ids = ",".join(map(str, self.entities)) or "0"
        return {int(e): s for e, s in self.q(f"select entity_id, state from lot_status where entity_id in ({ids})")}

    def at_work(self) -> int:
        return sum(1 for s in self.states().values() if s not in ("exported", "failed"))

    def running(self) -> None:
        """Lots are at work (the next order may be on its way)."""
        wait_for(lambda: self.at_work() > 0, 30, "lots at work")

    def done(self) -> bool:
        self.orders_from = ()
        states = self.states()
        failed = "select entity_id, reason from lot_status where state = 'failed'"
        assert "failed" not in states.values(), self.q(failed)
        assert not self.errors, self.errors
        with self._lock:
            return len(states) == len(self.entities) and set(states.values()) == {"exported"}

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            try:
                states = self.states()
                hosts = self.orders_from
                if hosts and sum(s not in ("exported", "failed") for s in states.values()) < self.keep:
                    self._turn += 1
                    self.order(hosts[self._turn % len(hosts)], "milled_pawn=2")
                for what, state in (("import", "waiting_import"), ("export", "waiting_export")):
                    if state in states.values():
                        r = self.cell.run("h2", what, "--all")
                        if r.returncode != 0:
                            self.errors.append(f"gwc {what} --all: {r.stderr}{r.stdout}")
            except Exception as e:  # told by done()
                self.errors.append(repr(e))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(60)


def new_agent(cell: Any, host: str) -> None:
    """The host's agent started again from the build now installed there (cell.builds): the old one
    killed (-9: the modules it started run on, docs/deploying.md, 5), the new one adopting them."""
    pid = int(json.loads((cell.var(host) / "run" / "agent.pid").read_text())["pid"])
    os.kill(pid, signal.SIGKILL)
    wait_for(lambda: gone(pid), 10, f"{host}'s old agent to go")
    cell.gwc(host, "start", timeout=240)


def walk_hosts(hosts: Any, cell: Any, url: str, build: Path) -> None:
    def q(text: str) -> list[list[Any]]:
        return sql_on(hosts, "h3", url, text)

    def versions(host: str) -> dict[str, Any]:
        return dict(json.loads(cell.gwc(host, "upgrade", "status", "--json", "--listen", "1")))

    def standbys_said(host: str) -> dict[str, int]:
        return {m: cell.log(host, m).count("standby: ") for m in SERVERS}

    def standing_by_again(host: str, said: dict[str, int]) -> None:
        now = standbys_said
        wait_for(lambda: all(now(host)[m] > n for m, n in said.items()), 60, f"{host}'s instances standing by")

    start_on_hosts(cell, q)
    record = cell.base / "monitor.jsonl"
    env = {**cell.env("h3"), "PYTHONPATH": str(build)}  # the new build's monitor: it reads both versions
    monitor = start_monitor(env, record, cwd=build, host=hosts["h3"])
    lots = Operator(cell, q, ("h3",))  # lots of the old build first, their scripts on h3
    try:
        wait_for(
            lambda: q("select 1 from machine_status where status in ('Setup', 'Running')"), 90, "a machine at work"
        )
        began = time.time()
        steps: dict[str, float] = {}

        # 1. The schema, from h2 with the new build installed: additive, the old build runs on.
        cell.builds["h2"] = build
        cell.gwc("h2", "db", "init")
        assert q("select version, compatible_from from schema_version") == [[NEW_SCHEMA, SCHEMA_VERSION]]
        steps["schema"] = time.time() - began

        # 2. h2: its agent and standbys restarted on the new build; they stand by again.
        said = standbys_said("h2")
        new_agent(cell, "h2")
        cell.gwc("h2", "restart", *SERVERS, timeout=120)
        standing_by_again("h2", said)
        assert {h for (h,) in q("select host from module_leases")} == {"h1"}  # nothing handed over yet
        steps["h2"] = time.time() - began

        # 3. h1: its agent on the new build, then the handover: h2's new instances take over, h1's
        # come back as standbys of the new build.
        lots.orders_from = ("h2", "h3")  # scripts of both builds, with the old machines
        lots.running()
        cell.builds["h1"] = build
        said = standbys_said("h1")
        new_agent(cell, "h1")
        handed = cell.gwc("h1", "upgrade", "handover", *SERVERS, timeout=240)
        for m in SERVERS:
            assert f"{m}: handed over to h2:" in handed, handed
        assert f"it speaks wire version {NEW_WIRE}" in handed, handed
        assert {h for (h,) in q("select host from module_leases")} == {"h2"}
        standing_by_again("h1", said)
        now = versions("h1")
        assert now["modules"]["msched"] == NEW_WIRE and now["modules"]["wc:wc1"] == wire.VERSION, now
        assert now["cell_speaks"] == wire.VERSION, now
        steps["h1"] = time.time() - began

        # 4. h3: its agent on the new build, then each machine in turn: shut down (after its run), its
        # WC and ME restarted from the new build, started again. The others go on working.
        # Old scripts as well as new ones see the machines upgraded under them: six queued on h3 first.
        lots.orders_from = ("h1",)
        lots.order("h3", "milled_pawn=6")
        cell.builds["h3"] = build
        new_agent(cell, "h3")
        for m in ("wc1", "wc2", "cmm_wc"):
            lots.running()
            cell.gwc("h3", "machine", "stop", m, timeout=120)
            cell.gwc("h3", "restart", f"me:{m}", f"wc:{m}", timeout=120)
            machine_start(cell, q, m)
            assert versions("h3")["modules"][f"wc:{m}"] == NEW_WIRE
        steps["h3"] = time.time() - began

        # Every lot exported; the old lot scripts gone, every member speaks the new version: the cell
        # moves up by itself, and a last lot runs in it.
        wait_for(lots.done, 300, "every lot exported", interval=1.0)
        wait_for(lambda: versions("h1")["cell_speaks"] == NEW_WIRE, 60, f"the cell to speak wire {NEW_WIRE}")
        moved = time.time()
        steps["moved up"] = moved - began
        lots.order("h1", "milled_pawn=1")
        wait_for(lots.done, 120, "the last lot exported", interval=1.0)
        ended = time.time()
    finally:
        lots.stop()
        stop_monitor(monitor)
    pawns = len(lots.entities)
    milled = q("select count(*) from machine_run_outcome where machine_id <> 'cmm_wc' and ack_code = 'ACK_OK'")
    assert milled[0][0] == pawns, f"{milled[0][0]} good milling runs for {pawns} pawns"  # none run twice
    check = cell.run("h2", "check")
    assert check.returncode == 0, check.stdout + check.stderr
    # During the walk: messages between the versions both ways, each in the older one, among them a
    # server's (h1 or h2) with a machine's WC (h3) of the other build, both ways; no module was sent a
    # version above the one it speaks; and the new modules already spoke the new version among themselves.
    said = talk(record, began, moved)
    mixed = between_versions(said)
    across = {(m.sender, m.to) for m in mixed if m.sender.startswith("wc:") != m.to.startswith("wc:")}
    assert any(s.startswith("wc:") for s, _ in across) and any(t.startswith("wc:") for _, t in across), across
    assert all(m.wire <= m.to_speaks for m in said), [m for m in said if m.wire > m.to_speaks][:5]
    new_talk = [m for m in said if m.wire == NEW_WIRE and m.sender.startswith("wc:") != m.to.startswith("wc:")]
    assert new_talk, "no message in the new version between the machines' host and the others during the walk"
    # Once the cell had moved up, only the new version.
    sent = wires(record)
    assert {v for at, v in sent if at > moved + 2} == {NEW_WIRE}, [(at - moved, v) for at, v in sent if at > moved]
    builds = collections.Counter(f"{b} build on {h}" for h, b in lots.entities.values())
    # A broadcast an old script cannot read (a new WC that heard from it longer than peer_timeout ago
    # speaks the new version again): it takes the run's outcome from the tables instead.
    unheard = sum(
        (cell.var(h) / "log" / f"lot-{e}.log").read_text(errors="replace").count("no RUN_COMPL came")
        for e, (h, b) in lots.entities.items()
        if b == "old" and (cell.var(h) / "log" / f"lot-{e}.log").exists()
    )
    print(
        f"rolling upgrade on namespace hosts: {ended - began:.0f}s; steps done at "
        + ", ".join(f"{k} {v:.0f}s" for k, v in steps.items())
        + f"; {pawns} pawns ({dict(builds)}), all exported, none failed, {milled[0][0]} milling runs;"
        f" monitor during the walk: {len(said)} messages to one module, {len(mixed)} between wire"
        f" {wire.VERSION} and {NEW_WIRE} modules (all in {wire.VERSION}), {len(new_talk)} in wire {NEW_WIRE}"
        f" between h3's WCs and the others; after the cell moved up "
        f"{sum(1 for at, v in sent if at > moved and v == NEW_WIRE)} in wire {NEW_WIRE}; old scripts' runs"
        f" whose outcome came from the tables, no RUN_COMPL read: {unheard}"
    )
