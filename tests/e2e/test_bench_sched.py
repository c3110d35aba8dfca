"""`gwc bench sched`, run small through the real CLI on the embedded cluster: it reports decisions
per second and free-to-bound latency, and leaves the cluster as it found it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

from gwc import db
from gwc.config import Config
from tests.conftest import TEST_PG_SETTINGS, PgCluster, make_config


def bench_sched(cfg: Config) -> list[dict[str, Any]]:
    env = {k: v for k, v in os.environ.items() if k != "GWC_DATABASE_URL"}
    env.update(GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var))
    args = ["--queued", "40", "--machines", "5", "--decisions", "10", "--samples", "5", "--json"]
    r = subprocess.run(
        [sys.executable, "-m", "gwc", "bench", "sched", *args], env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    result: list[dict[str, Any]] = json.loads(r.stdout)
    assert [x["queued"] for x in result] == [40] and result[0]["decisions"] > 0, result
    assert result[0]["decisions_per_s"] > 0
    return result


@pytest.mark.timeout(360)
def test_bench_sched_stops_the_embedded_cluster_it_started() -> None:
    base = Path(tempfile.mkdtemp(prefix="gwc-bench-sched-", dir="/var/tmp"))  # the postgres user reaches it
    base.chmod(0o755)
    cfg = make_config(base, None, database={"settings": TEST_PG_SETTINGS})
    try:
        assert cfg.embedded and not db.cluster_running(cfg)
        bench_sched(cfg)
        assert not db.cluster_running(cfg), "gwc bench sched left the cluster it started running"
    finally:
        db.cluster_stop(cfg)
        shutil.rmtree(base, ignore_errors=True)


def test_bench_sched_leaves_a_running_cluster_running(pg_cluster: PgCluster) -> None:
    bench_sched(pg_cluster.cfg)
    assert db.cluster_running(pg_cluster.cfg)
