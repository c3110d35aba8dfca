"""`gwc bench ...`: the benchmarks. Each lives in gwc/bench/<name>.py (the console's in gwc/console/cost.py)
and exposes `command`.

Benchmarks report medians and p99 and, where there is one, the bare floor measured in the same run
(these machines are shared and noisy, so only side-by-side figures compare).
"""

from __future__ import annotations

import importlib

import click

BENCH_MODULES = [
    "gwc.bench.bus",
    "gwc.bench.mq",
    "gwc.bench.sched",
    "gwc.bench.cell",
    "gwc.bench.growth",  # 10, 50, 100 machines in one table
    "gwc.bench.failover",
    "gwc.bench.order",
    "gwc.bench.opcua",
    "gwc.bench.quality",
    "gwc.console.cost",
    "gwc.hi.webbench",  # what open browsers on the web HMI cost
]


@click.group("bench")
def bench() -> None:
    """Measure the cell: the bus, the WC<->ME queues, the scheduler, the whole cell."""


for _name in BENCH_MODULES:
    bench.add_command(importlib.import_module(_name).command)

commands = [bench]
