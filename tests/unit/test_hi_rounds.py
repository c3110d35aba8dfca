"""The rounds bench (gwc/hi/rounds.py) without a cell: each load's figures are all made by a round
(the common ones and the load's own), and the two sides' medians are taken over their own rounds."""

from __future__ import annotations

from typing import Any

import pytest

from gwc.console.cost import ConsoleLoad
from gwc.hi.rounds import Load, compare
from gwc.hi.webbench import WebLoad

COMMON = {
    "lots_per_s",
    "overhead_median_ms",
    "overhead_p99_ms",
    "cell_cpu_ms_per_lot",
    "database_cpu_ms_per_lot",
    "db_commits_per_lot",
    "bus_msgs_per_lot",
}
GOT = {"loaded_cpu_ms_per_lot": {"sls": 1.0, "web": 2.0, "database": 3.0}, "seconds": 4.0}


def loads() -> list[Load]:
    return [ConsoleLoad("lots"), WebLoad(3)]


@pytest.mark.parametrize("load", loads(), ids=lambda load: load.side)
def test_every_figure_a_load_reports_is_made_by_a_round(load: Load) -> None:
    own = load.figures_of(True, GOT, 0.5, 10, 5)
    assert load.side in own, "a round says which side it is on"
    assert {key for _, key in load.figures} <= COMMON | set(own)


@pytest.mark.parametrize("load", loads(), ids=lambda load: load.side)
def test_each_side_is_the_median_of_its_own_rounds(load: Load) -> None:
    def round_(loaded: bool, x: float) -> dict[str, Any]:
        figures = dict.fromkeys(COMMON, x) | load.figures_of(loaded, GOT, x, 0, 1)
        return figures | {"lots_per_s": x}

    rounds = [round_(False, 1.0), round_(True, 10.0), round_(True, 30.0), round_(False, 3.0)]
    got = compare(rounds, load)
    assert got[f"median_without_{load.side}"]["lots_per_s"] == 2.0
    assert got[f"median_with_{load.side}"]["lots_per_s"] == 20.0
