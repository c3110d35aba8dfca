"""`gwc bench cell`, run small through the real CLI: it reports lots/s, overhead per lot, death to reroute,
the resting cell's CPU and whether `gwc check` held at the end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.harness import wait_for


def bench(tmp_path: Path, database_url: str, *args: str, timeout: float) -> dict[str, Any]:
    """`gwc bench ARGS --dir ... --json` on the session's database; its JSON once it exited 0."""
    env = dict(os.environ, GWC_DATABASE_URL=database_url, GWC_VAR=str(tmp_path / "var"))
    r = subprocess.run(
        [sys.executable, "-m", "gwc", "bench", *args, "--dir", str(tmp_path / "bench"), "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    result: dict[str, Any] = json.loads(r.stdout)
    return result


@pytest.mark.timeout(600)
def test_bench_cell_runs_lots_and_a_death_trial_and_reports_them(tmp_path: Path, database_url: str) -> None:
    result = bench(
        tmp_path,
        database_url,
        "cell",
        "--machines",
        "2",
        "--lots",
        "6",
        "--solo",
        "3",
        "--deaths",
        "1",
        "--idle",
        "2",
        timeout=540,
    )
    assert result["lots"] == 6 and result["failed"] == 0
    assert result["lots_per_s"] > 0
    assert result["loaded_overhead_ms"]["n"] == 6
    assert result["solo_lots"] == 3 and result["solo_failed"] == 0
    assert result["overhead_ms"]["n"] == 3 and 0 < result["overhead_ms"]["median"] < 5000
    every_phase = ("queued->bound", "bound->setup", "setup->started", "started->complete", "complete->unreserved")
    assert set(every_phase) <= set(result["phases_ms"]), (
        "a named event of the lot library (gwc/lot/events.py) went missing"
    )
    death = result["death_to_reroute_s"]
    assert death["n"] == 1 and 0 < death["median"] < 60
    # the resting cell's CPU, summed over its processes (servers, MSCHED, 2 WCs and MEs at least): the 2
    # machines asked for, the death trials' two stopped first
    assert {"msched", "ms", "ls", "wc", "me"} <= set(result["idle_cpu_percent_by_role"])
    assert 0 <= result["idle_cpu_percent"] < 100 and result["idle_machines"] == 2
    # its floor: one bare process for each bus member (MSCHED, 5 servers, the agent, 2 WCs), only waking
    assert result["idle_floor_processes"] == 9
    assert 0 < result["idle_floor_cpu_percent"] < 100
    assert result["check_held"] is True, result["check_breaches"]
    assert not list((tmp_path / "bench" / "run").glob("*.pid"))  # the bench stopped its cell
    # and kept to its folder: $GWC_VAR names another cell's
    assert (tmp_path / "bench" / "log" / "msched.log").exists()
    assert not (tmp_path / "var" / "log" / "msched.log").exists()


@pytest.mark.timeout(300)
def test_bench_console_compares_the_cell_with_and_without_a_console(tmp_path: Path, database_url: str) -> None:
    """`gwc bench console`: ABBA rounds on a real cell, the console in tmux; each side's figures reported."""
    result = bench(tmp_path, database_url, "console", "--machines", "2", "--lots", "5", "--pairs", "1", timeout=280)
    assert [r["console"] for r in result["rounds"]] == [False, True]  # one pair: without, then with
    without, with_console = result["median_without_console"], result["median_with_console"]
    assert without["lots_per_s"] > 0 and with_console["lots_per_s"] > 0
    assert without["console_cpu_ms_per_lot"] == 0 < with_console["console_cpu_ms_per_lot"]  # it found the console
    assert with_console["cell_cpu_ms_per_lot"] > 0
    assert result["check_held"] is True, result["check_breaches"]


def cell_processes(var: Path) -> list[int]:
    """Live processes started for the private cell under var (they carry GWC_VAR=var: PrivateCell.pids)."""
    mark = f"GWC_VAR={var.resolve()}".encode()
    found = []
    for d in Path("/proc").iterdir():
        try:
            if d.name.isdigit() and mark in (d / "environ").read_bytes().split(b"\0"):
                found.append(int(d.name))
        except OSError:
            continue
    return found


@pytest.mark.timeout(300)
def test_bench_cell_ended_by_sigterm_stops_its_cell(tmp_path: Path, database_url: str) -> None:
    """`timeout gwc bench cell ...`: the bench's SIGTERM stops its private cell too, as Ctrl-C does."""
    var = tmp_path / "bench"
    env = dict(os.environ, GWC_DATABASE_URL=database_url)
    args = ["--machines", "1", "--lots", "2", "--solo", "0", "--deaths", "0", "--idle", "600", "--dir", str(var)]
    bench = subprocess.Popen([sys.executable, "-m", "gwc", "bench", "cell", *args], env=env, stdout=subprocess.DEVNULL)
    try:
        wait_for(lambda: (var / "run" / "wc-wc1.pid").exists() and len(cell_processes(var)) >= 9, 120, "the cell up")
        bench.terminate()
        assert bench.wait(120) == 128 + signal.SIGTERM
        assert cell_processes(var) == []
        assert not list((var / "run").glob("*.pid"))
    finally:
        bench.kill()
        for pid in cell_processes(var):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.timeout(300)
def test_bench_order_runs_an_order_through_the_agent_and_reports_memory_and_connections(
    tmp_path: Path, database_url: str
) -> None:
    """`gwc bench order` small: 10 pawns, 3 machines (two mills, a CMM), at most 4 scripts at once."""
    result = bench(
        tmp_path, database_url, "order", "--parts", "10", "--machines", "3", "--max-running", "4", timeout=240
    )
    assert (result["parts"], result["mills"], result["cmms"], result["max_running"]) == (10, 2, 1, 4)
    assert result["exported"] == 10 and result["failed"] == 0
    assert 1 <= result["peak_scripts"] <= 4
    assert result["peak_memory_mb"] > 100, "every process of the cell counted, the lot scripts among them"
    assert 0 < result["peak_connections"] <= result["max_connections"]
    assert result["idle_while_waiting"] == 0
    assert result["check_ok"], result["check_failures"]
    assert not (tmp_path / "bench").exists(), "the private cell's folder is removed"


@pytest.mark.timeout(600)
def test_bench_growth_runs_each_size_and_reports_one_table(tmp_path: Path, database_url: str) -> None:
    """Two sizes, one after the other: a row each, the loaded overhead's growth against the first size,
    the whole cell's peak memory (PSS, the database included) and `gwc check` at each."""
    result = bench(
        tmp_path,
        database_url,
        "growth",
        *("--machines", "1,2", "--lots", "3,4", "--at-once", "1", "--solo", "0", "--idle", "1"),
        timeout=540,
    )
    rows = result["rows"]
    assert [(r["machines"], r["lots"]) for r in rows] == [(1, 3), (2, 4)]
    assert all(r["failed"] == 0 and r["check_held"] for r in rows), rows
    assert rows[0]["growth"] == 1.0 and rows[1]["growth"] > 0
    assert abs(rows[1]["growth"] - rows[1]["loaded_median_ms"] / rows[0]["loaded_median_ms"]) < 0.02
    # a cell of servers, MSCHED, machines and PostgreSQL takes far more than 50 MB, and less than 50 GB
    assert all(50 < r["peak_memory_mb"] < 50_000 for r in rows), rows
    assert all(r["resting_percent"] is not None and r["floor_percent"] is not None for r in rows)
    assert all(r["solo_median_ms"] is None for r in rows)  # --solo 0
    assert not list((tmp_path / "bench").glob("m*/run/*.pid")), "every size's cell stopped"
