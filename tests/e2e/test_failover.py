"""A host lost without stopping production (issue 36), on network-namespace hosts (gwc/netns.py).

h1 runs the active servers and MSCHED, h2 a standby of each (cell.toml `standby = ["h2"]`, started
by h2's agent), h3 the database and the machines. First h1 is cut off but alive: h2's standbys take
over, h1's instances depose themselves and, when the cable is back, stand by. Then h2's actives are
killed (-9) and h1's take over again; then h1 is killed whole (every process in it, and its cable)
while lots run: production resumes on h2, every lot is exported, nothing is run twice, `gwc check` is clean.

The lot scripts of step 3 run on h2; scripts on the host that dies are taken over by another
host's agent (tests/e2e/test_lot_hosts.py).
A long walk (about three minutes): `bin/test -m soak tests/e2e/test_failover.py`.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import psycopg
import pytest

from gwc.config import dump_toml
from gwc.netns import unavailable
from tests.e2e.test_hosts import HostCell, host_cell  # noqa: F401 (the fixture)
from tests.harness import SERVERS, wait_for

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.soak,
    pytest.mark.skipif(unavailable() is not None, reason=f"{unavailable()}"),
]

MACHINES = ("cmm_wc", "wc1", "wc2")
TTL = 3.0
BAR_S = 10.0  # the bar from the kill to production going on (its goal: 3 s)


class Redundant:
    """HostCell rearranged: servers on h1 with standbys on h2, the database and machines on h3."""

    def __init__(self, cell: HostCell) -> None:
        self.cell = cell
        doc = cell.doc
        doc["database"] = {**doc["database"], "host": "h3"}
        doc["module"] = [{"name": m, "host": "h1", "standby": ["h2"]} for m in SERVERS]
        doc["machine"] = [{**m, "host": "h3"} for m in doc["machine"] if m["id"] in MACHINES]
        doc["lease"] = {"ttl": TTL}
        for h in cell.hosts.hosts:
            own = {**doc, "cell": {"name": "hosts", "var": str(cell.var(h.name))}}
            cell.config_path(h.name).write_text(dump_toml(own))

    def query(self, text: str, *args: Any) -> list[tuple[Any, ...]]:
        url = f"postgresql://gwc@/gwc?host={self.cell.var('h3') / 'run' / 'pg'}"
        with psycopg.connect(url) as conn:
            return conn.execute(text, args).fetchall()

    def holders(self) -> dict[str, str]:
        return {n: h for n, h in self.query("select name, host from module_leases")}

    def start(self) -> None:
        c = self.cell
        c.gwc("h3", "start", timeout=240)
        for h in ("h1", "h2"):
            import shutil

            shutil.copytree(c.var("h3") / "secrets", c.var(h) / "secrets", dirs_exist_ok=True)
        c.gwc("h1", "start", timeout=240)  # first: its instances take the leases
        c.gwc("h2", "start", timeout=240)
        for m in MACHINES:
            self.start_machine(m)

    def start_machine(self, machine: str) -> None:
        import threading

        c = self.cell
        t = threading.Thread(target=lambda: c.gwc("h3", "machine", "start", machine))
        t.start()
        while t.is_alive():
            for (no,) in self.query(
                "select alarm_no from alarms where cleared_at is null and machine_id = %s and alarm_id = 'HOME_CMM'",
                machine,
            ):
                c.gwc("h3", "alarm", "clear", str(no))
            t.join(0.2)

    def order(self, host: str, items: str) -> list[int]:
        made = json.loads(self.cell.gwc(host, "order", "new", "--customer", "NJIT", items, "--json"))
        return [e for lot in made["lots"] for e in lot["entities"]]

    def done(self, host: str, entities: list[int]) -> bool:
        states = dict(self.query("select entity_id, state from lot_status where entity_id = any(%s)", entities))
        failed = {e: s for e, s in states.items() if s == "failed"}
        assert not failed, self.query("select entity_id, reason from lot_status where state = 'failed'")
        if "waiting_import" in states.values():
            self.cell.gwc(host, "import", "--all")
        if "waiting_export" in states.values():
            self.cell.gwc(host, "export", "--all")
        return len(states) == len(entities) and set(states.values()) == {"exported"}

    def last_binding(self) -> int:
        return int(
            self.query(
                "select greatest((select max(machine_run_id) from reserved_machines), "
                "(select max(machine_run_id) from machine_run_outcome), 0)"
            )[0][0]
        )

    def kill_host(self, host: str) -> None:
        """Every process of the host killed (-9) at once, then its cable cut."""
        ns = self.cell.hosts[host].netns
        pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split()
        for pid in pids:
            try:
                os.kill(int(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.cell.hosts.cut(host)

    def kill_modules(self, host: str) -> None:
        """kill -9 of the host's server processes (its agent restarts them, as standbys now)."""
        for m in SERVERS:
            pid_file = self.cell.var(host) / "run" / f"{m}.pid"
            if pid_file.exists():
                try:
                    os.kill(int(json.loads(pid_file.read_text())["pid"]), signal.SIGKILL)
                except (ProcessLookupError, ValueError, KeyError):
                    pass


@pytest.fixture
def redundant(host_cell: HostCell) -> Iterator[Redundant]:
    yield Redundant(host_cell)


def test_a_host_lost_cut_off_or_killed_does_not_stop_production(redundant: Redundant) -> None:
    r, cell = redundant, redundant.cell
    r.start()
    assert set(r.holders().values()) == {"h1"}, r.holders()

    # 1. h1 cut off, alive: after the ttl, h2's standbys fence h1's sessions and take over; h1's
    # instances, unable to renew, depose themselves (exit 75; h1's agent starts them as standbys).
    cell.hosts.cut("h1")
    cut_at = time.monotonic()
    wait_for(lambda: set(r.holders().values()) == {"h2"}, BAR_S + TTL, "h2's standbys to take every lease")
    took_cut = time.monotonic() - cut_at
    expired = r.query("select count(*) from lease_takeovers where how = 'expired' and host = 'h2'")[0][0]
    assert expired == len(SERVERS), expired
    # Fenced: no session of h1's instances is left in the database (the takeovers terminated them), so
    # nothing they still try can land. (h1's agent keeps its beat's session, gwc_agent: it writes only
    # its own host's beat, which says h1 is alive once the cable is back; its scripts are fenced by
    # lot_script_hosts, sql/092_lot_hosts.sql.)
    h1, h2 = cell.hosts["h1"].address, cell.hosts["h2"].address
    sessions_of_h1 = (
        "select count(*) from pg_stat_activity where client_addr = %s::inet and application_name <> 'gwc_agent'"
    )
    wait_for(lambda: r.query(sessions_of_h1, h1)[0][0] == 0, 10, "h1's sessions ended")
    entities = r.order("h2", "milled_pawn=2")  # production goes on from h2 while h1 is away
    wait_for(lambda: r.done("h2", entities), 90, "the lots made while h1 was cut off")
    wait_for(lambda: all("no longer the active" in cell.log("h1", m) for m in SERVERS), 10, "h1's instances deposed")
    time.sleep(max(0.0, 30 - (time.monotonic() - cut_at)))  # the 30 s cut, not a wait for a condition
    assert r.query(sessions_of_h1, h1)[0][0] == 0
    cell.hosts.mend("h1")
    # Back, they stand by: the leases stay with h2, and h1's instances say who is active.
    wait_for(lambda: all("standby: h2:" in cell.log("h1", m) for m in SERVERS), 30, "h1's instances standing by")
    assert set(r.holders().values()) == {"h2"}
    lock_holders = r.query(
        "select distinct host(a.client_addr) from pg_locks l join pg_stat_activity a using (pid) "
        "where l.locktype = 'advisory' and l.classid = 36036 and l.granted"
    )
    assert lock_holders == [(h2,)], lock_holders  # h1's sessions are back, none holds a lease

    # 2. h2's actives killed -9: h1's standbys take over at once (their sessions are gone).
    r.kill_modules("h2")
    wait_for(lambda: set(r.holders().values()) == {"h1"}, BAR_S, "h1's standbys to take over")
    wait_for(lambda: all(cell.log("h2", m).count("standby: h1:") >= 1 for m in SERVERS), 30, "h2 standing by again")

    # 3. h1 killed whole while lots run: production resumes on h2. The lots are ordered on h2, so
    # their scripts run there (a script does not outlive its host yet: docs/deploying.md).
    entities = r.order("h2", "milled_pawn=4")
    wait_for(lambda: r.done("h2", entities) or r.query("select 1 from machine_status where status = 'Running'"), 60,
             "a run")  # fmt: skip
    before = r.last_binding()
    r.kill_host("h1")
    killed = time.monotonic()
    wait_for(lambda: set(r.holders().values()) == {"h2"}, BAR_S, "h2 to take over from the dead h1")
    wait_for(lambda: r.done("h2", entities) or r.last_binding() > before, BAR_S * 3, "the next machine bound")
    resumed = time.monotonic() - killed
    wait_for(lambda: r.done("h2", entities), 120, "every lot exported")
    milled = r.query("select count(*) from machine_run_outcome where machine_id <> 'cmm_wc' and ack_code = 'ACK_OK'")[
        0
    ][0]
    assert milled == 6, f"{milled} good milling runs for 6 pawns"
    check = cell.run("h2", "check")
    assert check.returncode == 0, check.stdout + check.stderr
    print(f"cut (30 s): leases on h2 after {took_cut:.1f}s; kill: next binding {resumed:.1f}s after the kill")
