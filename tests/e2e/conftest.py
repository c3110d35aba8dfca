"""End-to-end fixtures: `cell` is a private cell on a fresh database (see tests/harness.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.e2e.lotkit import default_machines, lot_cell  # noqa: F401 (lot_cell: a fixture the lot tests share)
from tests.harness import CellHarness


@pytest.fixture
def make_cell(xprocess: Any, tmp_path: Path, database_url: str) -> Iterator[Any]:
    """Build a CellHarness with config overrides: make_cell(machines=[...], policy=..., faults=...)."""
    cells: list[CellHarness] = []

    def make(**config: Any) -> CellHarness:
        c = CellHarness(xprocess, tmp_path / f"cell{len(cells)}", database_url, **config)
        cells.append(c)
        return c

    yield make
    for c in cells:
        c.close()


@pytest.fixture
def cell(make_cell: Any) -> CellHarness:
    """A private cell with the default test machines: wc1, wc2 (dummy) and cmm_wc (CMM simulator)."""
    return make_cell(machines=default_machines())
