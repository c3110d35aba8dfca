"""Active and standby modules (issue 36): MSCHED and the Lot Server run with a standby each, the
database's lease decides which is active, and killing the active ones while lots run costs no lot.

One private cell on one host for every check (the lease does not care where its instances run;
tests/e2e/test_failover.py does the same over network-namespace hosts)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc.config import dump_toml, load_config
from gwc.lease import EXIT_DEPOSED
from tests.e2e.lotkit import (
    cell_with_machines,
    default_machines,
    gwc,
    import_export_all,
    ok,
    order,
    steps,
    stop_lot_scripts,
    wait_state,
)
from tests.harness import CellHarness, wait_for
from tests.leaks import MARK

pytestmark = pytest.mark.e2e

LEASED = ("msched", "ls")
TTL = 3.0  # the default: 2 s without a renewal and the holder deposes itself
BAR_S = 10.0  # the bar from the kill to production going on; its goal is 3 s


class Standbys:
    """Standby instances started by hand (`gwc run NAME`), as an agent on another host would."""

    def __init__(self, cell: CellHarness) -> None:
        self.cell = cell
        self.procs: list[subprocess.Popen[bytes]] = []
        self.names: dict[int, str] = {}  # pid -> module

    def start(self, name: str) -> subprocess.Popen[bytes]:
        out = open(self.cell.cfg.log_dir / f"standby-{name}-{len(self.procs)}.out", "wb")  # noqa: SIM115
        p = subprocess.Popen(
            [sys.executable, "-m", "gwc", "run", name],
            # Not the test's leak mark: a standby outlives the test that started it; the fixture stops it.
            env={k: v for k, v in self.cell.env().items() if k != MARK},
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        out.close()
        self.procs.append(p)
        self.names[p.pid] = name
        return p

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def leased_cell(make: Any) -> CellHarness:
    cell: CellHarness = make(machines=default_machines(run_time=0.6), sections={"lease": {"ttl": TTL, "poll": 0.1}})
    doc = tomllib.loads(cell.cfg.path.read_text())
    for m in doc["module"]:
        if m["name"] in LEASED:
            m["lease"] = True
    cell.cfg.path.write_text(dump_toml(doc))
    cell.cfg = load_config(cell.cfg.path)
    return cell


@pytest.fixture(scope="module")
def redundant(xprocess: Any, tmp_path_factory: pytest.TempPathFactory, pg_cluster: Any) -> Iterator[Any]:
    """One cell for the module's checks: every server, MSCHED and the Lot Server leased, machines up."""
    import uuid

    from psycopg import sql

    name = f"gwc_t_{uuid.uuid4().hex[:12]}"
    with pg_cluster.admin() as conn:
        conn.execute(
            sql.SQL("create database {} template {}").format(sql.Identifier(name), sql.Identifier(pg_cluster.template))
        )
    cell = leased_cell(
        lambda **c: CellHarness(xprocess, tmp_path_factory.mktemp("redundant"), pg_cluster.url(name), **c)
    )
    standbys = Standbys(cell)
    try:
        cell_with_machines(cell, "wc1", "wc2", "cmm_wc")
        for name in LEASED:  # started here, not in a test: they outlive it (the leak checker's mark)
            standbys.start(name)
        yield cell, standbys
    finally:
        stop_lot_scripts(cell)
        cell.close()  # machines first, while the active MSCHED and Lot Server (the standbys now) still answer
        standbys.close()
        with pg_cluster.admin() as conn:
            conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))


def gone(pid: int) -> bool:
    """The process exited (a zombie its parent, xprocess, has not reaped counts)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def holder(cell: CellHarness, name: str) -> tuple[int, str]:
    rows = cell.query("select epoch, holder from module_leases where name = %s", name)
    return (int(rows[0][0]), str(rows[0][1])) if rows else (0, "")


def holder_pid(cell: CellHarness, name: str) -> int:
    return int(holder(cell, name)[1].split(":")[1])


def standing_by(cell: CellHarness, name: str, n: int) -> bool:
    return cell.log_text(name).count("standby: ") >= n


def started_anew(cell: CellHarness, name: str, old_inc: int) -> bool:
    peer = cell.bus.peers().get(name)
    return peer is not None and peer.inc != old_inc and "SHUTDOWN" in peer.interest


def no_run_twice(cell: CellHarness, entities: list[int]) -> None:
    owner: dict[int, int] = {}
    for e in entities:
        done = [s["op_type"] for s in steps(cell, e) if s.get("runs")]
        assert len(done) == len(set(done)), f"entity {e} ran an operation twice: {done}"
        for s in steps(cell, e):
            assert owner.setdefault(int(s["machine_run_id"]), e) == e, f"run {s['machine_run_id']} of two entities"


def test_kill_9_of_the_active_msched_and_lot_server_while_lots_run_a_standby_takes_over(redundant: Any) -> None:
    cell, _standbys = redundant
    for name in LEASED:
        wait_for(lambda name=name: standing_by(cell, name, 1), 20, f"a standby {name}")
    epochs = {name: holder(cell, name)[0] for name in LEASED}
    entities = order(cell, "milled_pawn=3")
    for e in entities:
        wait_state(cell, e, "waiting_import")
    ok(gwc(cell, "import", "--all"))
    wait_for(
        lambda: cell.query("select count(*) from machine_status where status in ('Setup', 'Running')")[0][0] > 0,
        30,
        "a machine at work",
    )
    incs = {name: cell.bus.peers()[name].inc for name in LEASED}
    killed = time.monotonic()
    for name in LEASED:
        cell.kill(name)
    took: dict[str, float] = {}
    for name in LEASED:
        wait_for(lambda name=name: started_anew(cell, name, incs[name]), BAR_S, f"the standby {name} to take over")
        took[name] = time.monotonic() - killed
    assert max(took.values()) < BAR_S, took
    for name in LEASED:
        epoch, _ = holder(cell, name)
        assert epoch == epochs[name] + 1
        assert cell.query("select how from lease_takeovers where name = %s and epoch = %s", name, epoch) == [("free",)]
    # Production goes on: the next machine bound after the kill, and every lot exported.
    import_export_all(cell, entities, timeout=90)
    no_run_twice(cell, entities)
    print(f"takeover after kill -9: {', '.join(f'{n} {t:.2f}s' for n, t in took.items())}")


@pytest.mark.soak  # 15 s more on a shared cell; tests/unit/test_lease.py proves the fencing in the default suite
def test_a_stalled_active_is_fenced_deposes_itself_and_its_writes_do_not_land(redundant: Any) -> None:
    """The active MSCHED stopped (SIGSTOP: alive, its session open, silent) longer than its lease:
    the standby fences its session and takes over; resumed, the old instance finds itself deposed,
    serves nothing, leaves the bus and exits EXIT_DEPOSED (its agent would start it a standby)."""
    cell, standbys = redundant
    name = "msched"
    old = holder_pid(cell, name)
    waiting = [p for p in standbys.procs if p.poll() is None and p.pid != old and standbys.names[p.pid] == name]
    if not waiting:
        standbys.start(name)  # it will be the active one: the fixture stops it after the cell
    wait_for(lambda: standing_by(cell, name, 1 + (not waiting)), 20, "a standby msched")
    fenced(cell, standbys, name, old)


def fenced(cell: CellHarness, standbys: Standbys, name: str, old: int) -> None:
    epoch = holder(cell, name)[0]
    inc = cell.bus.peers()[name].inc
    os.kill(old, signal.SIGSTOP)
    try:
        stopped = time.monotonic()
        wait_for(lambda: started_anew(cell, name, inc), BAR_S + TTL, "the standby to take over from the stalled one")
        took = time.monotonic() - stopped
        assert holder(cell, name)[0] == epoch + 1
        assert cell.query("select how from lease_takeovers where name = %s and epoch = %s", name, epoch + 1) == [
            ("expired",)
        ]
    finally:
        os.kill(old, signal.SIGCONT)
    proc = next((p for p in standbys.procs if p.pid == old), None)
    wait_for(lambda: gone(old) or (proc is not None and proc.poll() is not None), 15, "the deposed msched to exit")
    if proc is not None:
        assert proc.returncode == EXIT_DEPOSED
    assert "no longer the active msched" in cell.log_text(name)
    # The new one serves; then it hands over as an upgrade does (docs/deploying.md, 7): a standby
    # waits, the active is stopped (SIGTERM, as `gwc restart` does), the standby takes the lease at
    # once, and a lot ordered across the hand-over goes through.
    said = cell.log_text(name).count("standby: ")
    standbys.start(name)
    wait_for(lambda: standing_by(cell, name, said + 1), 20, "a new standby")
    entities = order(cell, "milled_pawn=2")
    inc = cell.bus.peers()[name].inc
    epoch = holder(cell, name)[0]
    os.kill(holder_pid(cell, name), signal.SIGTERM)
    wait_for(lambda: started_anew(cell, name, inc), BAR_S, "the standby to take over from the stopped one")
    assert cell.query("select how from lease_takeovers where name = %s and epoch = %s", name, epoch + 1) == [("free",)]
    import_export_all(cell, entities, timeout=60)
    no_run_twice(cell, entities)
    print(f"takeover from a stalled active: {took:.2f}s (ttl {TTL}s)")
