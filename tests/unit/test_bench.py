"""The benchmarks' shared parts (gwc/bench/__init__.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from gwc.bench import percentile, reaped_cpu_s

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
