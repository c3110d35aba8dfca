"""The per-host agent (gwc/agent/): restarts what dies, announces each death, gives up on a module that
cannot start, survives its own death. Driven through the real CLI on a private cell."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc.agent import control as agent_control
from gwc.ipc.bus import BlockingBus
from tests.e2e.test_cell import gwc
from tests.harness import wait_for, write_cell_config
from tests.leaks import open_files

pytestmark = pytest.mark.e2e

# The bar: RUNNING again this soon after a kill -9, without an operator. Measured from the
# test's kill to the moment the agent recorded the new process RUNNING (its `running_at`, on the
# host's one monotonic clock), so neither this test's polling nor a slow `gwc status` counts.
BACK_WITHIN = 3.0


def status(env: dict[str, str]) -> dict[str, dict[str, Any]]:
    out = gwc(env, "status", "--json")
    assert out.returncode == 0, out.stderr
    return {r["module"]: r for r in json.loads(out.stdout)}


def agent_rows(cfg: Any) -> dict[str, dict[str, Any]]:
    return {r["module"]: r for r in agent_control.call(cfg, "status")["modules"]}


def agent_pid(cfg: Any) -> int:
    return int(json.loads((cfg.run_dir / "agent.pid").read_text())["pid"])


@pytest.fixture
def agent_cell(tmp_path: Path, database_url: str):
    def make(machines: list[dict[str, Any]]) -> tuple[Any, dict[str, str]]:
        cfg = write_cell_config(tmp_path / "var", database_url, machines=machines)
        env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=database_url)
        made.append(env)
        return cfg, env

    made: list[dict[str, str]] = []
    yield make
    for env in made:
        gwc(env, "stop")


@pytest.mark.alone  # timed against a bar: run with no other test beside it
def test_kill_9_of_each_module_kind_is_announced_and_running_again_within_3s(agent_cell) -> None:
    cfg, env = agent_cell([{"id": "wc1", "kind": "dummy", "run_time": 0.1}])
    started = gwc(env, "start")
    assert started.returncode == 0, started.stderr + started.stdout
    before = status(env)
    assert all(r["state"] == "RUNNING" for r in before.values()), before
    log = logging.getLogger("test")
    with BlockingBus("test.deaths", cfg.bus, log, interest=("MOD_DIED",)) as bus:
        for name in ("msched", "ms", "ls", "cas", "ers", "sls", "wc:wc1", "me:wc1"):
            old = status(env)[name]
            killed_at = time.monotonic()
            os.kill(old["pid"], signal.SIGKILL)
            conv = bus.first_message(timeout=5)
            assert conv is not None and conv.first is not None, f"no Module_Died for {name}"
            died = conv.first.first
            conv.end()
            assert (died.module, died.pid, died.how) == (name, old["pid"], "killed by SIGKILL"), died
            assert died.restart_in == 0.0
            now = wait_for(  # asked of the agent in-process: a `gwc status` process takes a while to start
                lambda n=name, p=old["pid"]: (r := agent_rows(cfg)[n])["state"] == "RUNNING" and r["pid"] != p and r,
                10,
                f"{name} RUNNING again",
                interval=0.05,
            )
            noticed, back = now["died_at"] - killed_at, now["running_at"] - killed_at
            assert noticed < 0.5, f"the agent noticed {name}'s death {noticed:.2f}s after the kill"
            assert back < BACK_WITHIN, f"{name} RUNNING again {back:.2f}s after its kill"
            assert now["restarts"] == old["restarts"] + 1 and now["last_exit"] == "killed by SIGKILL"

    # The agent killed: its modules run on; a new agent adopts them rather than start them twice.
    pids = {n: r["pid"] for n, r in status(env).items()}
    os.kill(agent_pid(cfg), signal.SIGKILL)
    wait_for(lambda: "not running" in gwc(env, "status").stdout, 10, "status to say the agent is gone")
    assert {n: r["pid"] for n, r in status(env).items()} == pids
    again = gwc(env, "start")
    assert again.returncode == 0, again.stderr + again.stdout
    adopted = status(env)
    assert {n: r["pid"] for n, r in adopted.items()} == pids
    assert all(r["state"] == "RUNNING" for r in adopted.values()), adopted
    os.kill(pids["ls"], signal.SIGKILL)  # watched again: restarted
    wait_for(lambda: (r := status(env)["ls"])["state"] == "RUNNING" and r["pid"] != pids["ls"], 10, "ls restarted")

    # gwc restart goes through the agent.
    restarted = gwc(env, "restart", "msched")
    assert restarted.returncode == 0, restarted.stderr
    after = status(env)["msched"]
    assert after["state"] == "RUNNING" and after["pid"] != pids["msched"]
    bad = gwc(env, "restart", "nosuch")
    assert bad.returncode != 0 and "no module nosuch" in bad.stderr

    stopped = gwc(env, "stop")
    assert stopped.returncode == 0, stopped.stderr
    assert not list(cfg.run_dir.glob("*.pid"))


TWO_MILLINGS = '''"""Mill a pawn twice: two operation steps, so that a restart can fall in either."""

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    runs = [entity.operate("mill_chess").machine_run_id for _ in range(2)]
    entity.lot_completed(f"PASS: runs {runs[0]} {runs[1]}")
    entity.wait_for_export()
'''


@pytest.mark.alone  # timed against a bar: run with no other test beside it
def test_a_lot_script_killed_9_mid_run_is_running_again_within_3s_and_its_lot_is_done_once(
    agent_cell, tmp_path: Path, database_url: str
) -> None:
    """Two lots of two millings each; one script killed -9 in its first run, the other in its second.
    The agent restarts each (RUNNING again within 3 s of the kill, by the agent's own clock), the new
    process takes its run up where it is, and every lot is exported having milled twice: 4 runs in all."""
    cfg, env = agent_cell([{"id": m, "kind": "dummy", "run_time": 1.0} for m in ("wc1", "wc2")])
    assert gwc(env, "start").returncode == 0
    for m in ("wc1", "wc2"):
        assert gwc(env, "machine", "start", m).returncode == 0
    script = tmp_path / "two_millings.py"
    script.write_text(TWO_MILLINGS)
    assert gwc(env, "script", "register", "two_millings", str(script), "--product", "pawn2").returncode == 0
    made = gwc(env, "order", "new", "--customer", "NJIT", "pawn2=2", "--json")
    assert made.returncode == 0, made.stderr
    entities = [e for lot in json.loads(made.stdout)["lots"] for e in lot["entities"]]

    def query(sql: str, *params: Any) -> list[tuple[Any, ...]]:
        with psycopg.connect(database_url) as conn:
            return conn.execute(sql, params).fetchall()

    def states() -> dict[int, str]:
        return dict(query("SELECT entity_id, state FROM lot_status WHERE entity_id = ANY(%s)", entities))

    wait_for(lambda: set(states().values()) == {"waiting_import"}, 30, "the lots to ask to be imported")
    assert gwc(env, "import", "--all").returncode == 0

    def kill_in_run(entity: int, operation: int) -> None:
        def running() -> bool:
            ops = (json.loads((cfg.var / "lots" / f"entity-{entity}.json").read_text()).get("operations")) or []
            rows = query(
                "SELECT s.status FROM reserved_machines r JOIN machine_status s USING (machine_id, machine_run_id) "
                "WHERE r.entity_id = %s",
                entity,
            )
            return len(ops) == operation and rows == [("Running",)]

        wait_for(running, 30, f"entity {entity}'s run {operation} to be Running", interval=0.05)
        kill_lot(entity, restarts=1)

    def kill_lot(entity: int, restarts: int) -> None:
        old = agent_rows(cfg)[f"lot:{entity}"]
        forked_by_the_agent(cfg, old["pid"], entity)
        killed_at = time.monotonic()
        os.kill(old["pid"], signal.SIGKILL)
        (cfg.run_dir / f"lot-{entity}.pid").unlink(missing_ok=True)  # as `gwc soak` does: the agent needs it not
        new = wait_for(
            lambda: (r := agent_rows(cfg)[f"lot:{entity}"])["pid"] != old["pid"] and r["state"] == "RUNNING" and r,
            20,
            f"lot:{entity} RUNNING again",
        )
        back = new["running_at"] - killed_at  # the agent's own record (one clock for the host), not this loop's
        assert back < BACK_WITHIN, f"lot:{entity} RUNNING again {back:.2f}s after its kill"
        assert new["restarts"] == restarts and new["last_exit"] == "killed by SIGKILL", new

    kill_in_run(entities[0], 1)
    kill_in_run(entities[1], 2)
    # Killed again once its lot is done and waits to be exported: the new process replays both
    # operations and goes on waiting for the export.
    wait_for(lambda: states()[entities[0]] == "waiting_export", 30, "the first lot to wait for its export")
    kill_lot(entities[0], restarts=2)
    log_0 = cfg.log_dir / f"lot-{entities[0]}.log"
    wait_for(lambda: "waiting to be exported" in log_0.read_text().split("resumes after")[-1], 20, "the replay")

    def all_out() -> bool:
        now = states()
        assert "failed" not in now.values(), query("SELECT entity_id, reason FROM lot_status")
        if "waiting_export" in now.values():
            gwc(env, "export", "--all")
        return set(now.values()) == {"exported"}

    wait_for(all_out, 60, "both lots exported", interval=0.2)
    runs = query("SELECT machine_run_id, ack_code FROM machine_run_outcome")
    assert len(runs) == 4 and {c for _, c in runs} == {"ACK_OK"}, runs  # two millings per lot, none twice
    for e in entities:
        traveller = json.loads((cfg.var / "lots" / f"entity-{e}.json").read_text())
        assert traveller["restarts"] == (2 if e == entities[0] else 1), traveller
        codes = [list(op["codes"].values()) for op in traveller["operations"]]
        assert codes == [["ACK_OK"], ["ACK_OK"]], traveller
        text = (cfg.log_dir / f"lot-{e}.log").read_text()
        # Taken up mid-run; on a loaded machine the kill can land just after the run completed instead.
        resumed = ("is taken up where it is", "completed while the lot script was down", "was done before the restart")
        assert any(r in text.split("resumes after")[1] for r in resumed), text[-3000:]
    checked = gwc(env, "check")
    assert checked.returncode == 0, checked.stdout + checked.stderr
    # The agent reaped each script it forked, and logged what its whole process cost.
    text = next(cfg.log_dir.glob("agent-*.log")).read_text()
    for e in entities:
        assert re.search(rf"lot:{e}: RUNNING -> STOPPED .*exited 0, \d+ ms of CPU: its work is done", text), e


def forked_by_the_agent(cfg: Any, pid: int, entity: int) -> None:
    """A lot script is a fork of the agent (gwc.lot.run.fork_lot_script): its child, in a session of its own,
    named lot:E, holding nothing of the agent's (its lock, its sockets): a new agent can take over."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    assert (int(fields[1]), int(fields[3])) == (agent_pid(cfg), pid), fields[:4]
    # A fork copies only the thread that forks: the agent must run none besides (fork_lot_script).
    assert len(list(Path(f"/proc/{agent_pid(cfg)}/task").iterdir())) == 1, "the agent runs a thread"
    assert Path(f"/proc/{pid}/comm").read_text().strip() == f"lot:{entity}"

    def fds(of: int) -> set[str]:  # an epoll or pidfd has no identity here
        return {t for t in open_files(of) if not t.startswith("anon_inode:")}

    held = fds(pid) & fds(agent_pid(cfg))
    assert held <= {"/dev/null", str(cfg.log_dir / f"lot-{entity}.out")}, held


def test_a_module_failing_at_every_start_ends_fatal_with_an_alarm(agent_cell) -> None:
    cfg, env = agent_cell([{"id": "wc1", "kind": "dummy", "run_time": "not a number"}])
    started = gwc(env, "start")
    assert started.returncode != 0
    assert "me:wc1 is FATAL" in started.stderr, started.stderr
    rows = status(env)
    assert rows["me:wc1"]["state"] == "FATAL" and rows["me:wc1"]["pid"] is None, rows["me:wc1"]
    assert rows["msched"]["state"] == "RUNNING"
    alarms = wait_for(
        lambda: [a for a in json.loads(gwc(env, "alarm", "list", "--json").stdout) if a["alarm_id"] == "MODULE_FATAL"],
        10,
        "alarm MODULE_FATAL",
    )
    assert "me:wc1" in alarms[0]["alarm_text"] and alarms[0]["machine_id"] == "wc1", alarms
    log = (cfg.log_dir).glob("agent-*.log")
    text = next(log).read_text()
    assert "me:wc1: STARTING -> BACKOFF" in text and "me:wc1: STARTING -> FATAL" in text


@pytest.mark.soak
def test_both_cores_saturated_for_60s_no_machine_is_shut_down(agent_cell, database_url: str) -> None:
    machines = [{"id": f"wc{i}", "kind": "dummy", "run_time": 0.2} for i in (1, 2)]
    cfg, env = agent_cell(machines)
    assert gwc(env, "start").returncode == 0
    for m in machines:
        started = gwc(env, "machine", "start", m["id"])
        assert started.returncode == 0, started.stderr
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 2)]
    t0 = time.monotonic()
    try:

        def sixty_seconds_all_up() -> bool:
            with psycopg.connect(database_url) as conn:
                rows = conn.execute(  # the cell's machines: the seeded database knows others, all Shutdown
                    "SELECT machine_id, status, note FROM machine_status WHERE machine_id = ANY(%s)",
                    ([m["id"] for m in machines],),
                ).fetchall()
            assert len(rows) == len(machines), rows
            down = [r for r in rows if r[1] != "Idle"]
            assert not down, f"after {time.monotonic() - t0:.0f}s of saturation: {down}"
            return time.monotonic() - t0 >= 60

        wait_for(sixty_seconds_all_up, 120, "60 s of both cores saturated", interval=0.5)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert all(r["restarts"] == 0 and r["state"] == "RUNNING" for r in status(env).values())
