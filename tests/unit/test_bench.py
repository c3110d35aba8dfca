"""The benchmarks' shared parts (gwc/bench/__init__.py)."""

from __future__ import annotations

import itertools
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import click
import pytest

from gwc.bench import logs, percentile, reaped_cpu_s
from gwc.lot import events
from gwc.lot.events import Phase

PHASE_LIST = list(Phase)

# In a child process: pytest's own CPUs stay as they are.
PLACE = """
import os, sys
from gwc.bench import pin_cpu
pin_cpu(int(sys.argv[1]), [int(c) for c in sys.argv[2].split(",")])
print(",".join(map(str, sorted(os.sched_getaffinity(0)))))
"""


def placed(which: int, cpus: list[int]) -> str:
    done = subprocess.run(
        [sys.executable, "-c", PLACE, str(which), ",".join(map(str, cpus))], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_pin_cpu_puts_each_end_of_a_ping_pong_on_its_own_cpu() -> None:
    cpus = sorted(os.sched_getaffinity(0))[:2]
    assert placed(0, cpus) == str(cpus[0])
    assert placed(1, cpus) == str(cpus[1])
    assert placed(2, cpus) == str(cpus[0])  # wraps round


def test_pin_cpu_leaves_a_single_cpu_alone() -> None:
    mine = ",".join(map(str, sorted(os.sched_getaffinity(0))))
    assert placed(1, [sorted(os.sched_getaffinity(0))[0]]) == mine


def test_percentile_is_by_nearest_rank() -> None:
    values = list(range(1, 101))
    assert percentile(values, 50) == 50 and percentile(values, 99) == 99 and percentile(values, 100) == 100
    assert percentile([7.0], 99) == 7.0
    assert percentile([], 50) != percentile([], 50)  # NaN


def test_reaped_cpu_s_counts_the_children_a_process_waited_for() -> None:
    before = reaped_cpu_s(os.getpid())
    # A child that burns about 0.2 s of CPU, then is reaped: its time is ours as a parent's.
    subprocess.run(
        [sys.executable, "-c", "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.2: pass"],
        check=True,
    )
    assert reaped_cpu_s(os.getpid()) - before >= 0.15


def test_the_cell_bench_times_phases_from_named_events_not_log_wording() -> None:
    """Each phase `gwc bench cell` times is a named event the lot library emits (gwc/lot/events.py):
    the log line's words may change, the event stays, and the bench reads the event only."""
    lot_source = "".join(p.read_text() for p in (Path(__file__).parents[2] / "gwc" / "lot").rglob("*.py"))
    for phase in Phase:
        assert f"event(Phase.{phase.name}" in lot_source, f"the lot library no longer emits {phase}"
    log = logging.getLogger("test.bench.events")
    log.setLevel(logging.INFO)
    recorder = events.record(log)
    try:
        for phase, machine in [(Phase.QUEUED, None), (Phase.BOUND, "wc2"), *[(p, "wc2") for p in PHASE_LIST[2:]]]:
            log.info("any wording at all %s", phase, extra=events.event(phase, machine))
            time.sleep(0.002)
        log.info("a line that marks nothing")
    finally:
        log.removeHandler(recorder)
    marks = recorder.as_list()
    assert [m[0] for m in marks] == [p.value for p in Phase]
    timed = logs.phases(marks)
    assert list(timed) == [f"{a}->{b}" for a, b in itertools.pairwise(logs.PHASES)]
    assert all(v > 0 for v in timed.values())
    assert logs.bound_to(marks, "wc2", marks[0][1]) == marks[1][1]
    assert logs.bound_to(marks, "wc1", 0) is None


def test_growth_sizes_pair_machines_with_lots_and_refuse_a_mismatch() -> None:
    from gwc.bench.growth import sizes

    assert sizes("10,50,100", "500,2000,5000") == [(10, 500), (50, 2000), (100, 5000)]
    for machines, lots in (("10,50", "500"), ("ten", "5"), ("0", "5"), ("", "")):
        with pytest.raises(click.BadParameter):
            sizes(machines, lots)


def test_growth_rows_are_measured_against_the_first_size() -> None:
    from gwc.bench.growth import row_of, table

    def result(machines: int, median: float) -> dict[str, Any]:
        return {
            "machines": machines,
            "lots": 10 * machines,
            "failed": 0,
            "lots_per_s": 12.345,
            "loaded_overhead_ms": {"median": median, "p99": 2 * median},
            "idle_cpu_percent": 1.5,
            "idle_floor_cpu_percent": 0.5,
            "peak_memory_mb": 900.0,
            "check_held": True,
        }

    first = row_of(result(10, 40.0), None)
    second = row_of(result(50, 50.0), first.loaded_median_ms)
    assert (first.growth, second.growth) == (1.0, 1.25)
    assert second.solo_median_ms is None and second.lots_per_s == 12.35
    text = table([first, second], 10)
    assert "10 at once" in text and "1.25" in text and text.count("held") == 2
