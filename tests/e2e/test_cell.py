"""`gwc start`, `gwc status`, `gwc stop` on a whole cell, driven through the real CLI."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gwc.cell import cell_procs, pid_file
from gwc.ipc.mq import queue_exists, queue_names
from gwc.log import log_file_name
from tests.harness import wait_for, write_cell_config

FIGURE2 = re.compile(
    r"^From \S+ \| Date \d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} \| User \S+ \| Term \S+ \| PID \d+ \| "
    r"Module \S+ \| Conv .+ \| (Trace|Note|Warning|Error): .*$"
)
MACHINES = [{"id": "wc1", "kind": "dummy", "run_time": 0.1}, {"id": "wc2", "kind": "dummy", "run_time": 0.1}]


def gwc(env: dict[str, str], *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=env, capture_output=True, text=True, timeout=timeout
    )


@pytest.fixture
def cell_env(tmp_path: Path, database_url: str):
    cfg = write_cell_config(tmp_path / "var", database_url, machines=MACHINES)
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=database_url)
    yield cfg, env
    gwc(env, "stop")  # whatever the test did, leave nothing running


def test_start_status_kill_stop_leaves_nothing_behind(cell_env) -> None:
    cfg, env = cell_env
    started = gwc(env, "start")
    assert started.returncode == 0, started.stderr + started.stdout
    procs = cell_procs(cfg)
    assert {p.name for p in procs} >= {"cas", "ers", "ms", "ls", "sls", "msched", "wc:wc1", "me:wc1", "wc:wc2"}

    status = json.loads(gwc(env, "status", "--json").stdout)
    assert all(row["alive"] == "yes" for row in status), status
    pids = {row["module"]: row["pid"] for row in status}
    assert len(set(pids.values())) == len(procs), "every module is its own process"

    for p in procs:  # each has its own log, in Figure 2 form
        lines = (cfg.log_dir / log_file_name(p.name)).read_text().splitlines()
        assert lines, f"{p.name} wrote no log"
        assert all(FIGURE2.match(line) for line in lines), [ln for ln in lines if not FIGURE2.match(ln)][:3]
    assert "STARTUP" in (cfg.log_dir / "msched.log").read_text()
    # WCs do not track each other (WC.ignored_peers): neither logs the other joining; the Machine Server both.
    wait_for(
        lambda: all(f"wc:{m} joined the bus" in (cfg.log_dir / "ms.log").read_text() for m in ("wc1", "wc2")),
        10,
        "the Machine Server to know both WCs",
    )
    for me, other in (("wc1", "wc2"), ("wc2", "wc1")):
        assert f"wc:{other} joined" not in (cfg.log_dir / log_file_name(f"wc:{me}")).read_text()

    os.kill(pids["msched"], signal.SIGKILL)  # the agent restarts it; the others go on undisturbed
    wait_for(
        lambda: (
            (r := {r["module"]: r for r in json.loads(gwc(env, "status", "--json").stdout)}["msched"])["alive"] == "yes"
            and r["pid"] != pids["msched"]
        ),
        10,
        "gwc status to show msched running again",
    )
    assert gwc(env, "start").returncode == 0  # idempotent: starts only what is missing
    again = {r["module"]: r for r in json.loads(gwc(env, "status", "--json").stdout)}
    assert again["msched"]["alive"] == "yes" and again["msched"]["pid"] != pids["msched"]
    assert again["ms"]["pid"] == pids["ms"]
    pids["msched"] = again["msched"]["pid"]

    stopped = gwc(env, "stop")
    assert stopped.returncode == 0, stopped.stderr
    for pid in pids.values():
        wait_for(
            lambda pid=pid: (
                not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]
            ),
            10,
            f"pid {pid} to be gone",
        )
    assert not list(cfg.run_dir.glob("*.pid"))
    for m in MACHINES:
        assert not any(queue_exists(q) for q in queue_names(cfg.ipc_prefix, m["id"]))
    assert not pid_file(cfg, "msched").exists()

    second = gwc(env, "stop")
    assert second.returncode == 0, second.stderr


def test_start_with_database_down_is_one_clear_error(tmp_path: Path) -> None:
    dead = tmp_path / "nosocket"
    dead.mkdir()
    url = f"postgresql://gwc@/gwc?host={dead}&connect_timeout=1"
    cfg = write_cell_config(tmp_path / "var", url, machines=MACHINES)
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=url)
    try:
        result = gwc(env, "start")
        assert result.returncode != 0
        err = result.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("gwc: "), result.stderr
        assert "Traceback" not in result.stderr + result.stdout
        assert "database" in err[0].lower()
    finally:
        gwc(env, "stop")
