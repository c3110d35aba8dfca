"""`gwc bench failover` (issue 36): the active servers killed while lots run, N trials; a smoke run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.soak]


def test_bench_failover_measures_the_resume_and_loses_no_lot(tmp_path: Path, database_url: str) -> None:
    env = dict(os.environ, GWC_DATABASE_URL=database_url, GWC_VAR=str(tmp_path / "var"))
    out = subprocess.run(
        [sys.executable, "-m", "gwc", "bench", "failover", "--trials", "2", "--json", "--dir", str(tmp_path / "b")],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout)
    assert r["trials"] == 2
    assert set(r["resume_s"]) == {"median", "p99", "max"}
    assert r["resume_s"]["max"] < 10.0, r  # the bar
    assert (r["lots_lost"], r["runs_twice"], r["rows_lost"], r["lots_failed"]) == (0, 0, 0, 0), r
