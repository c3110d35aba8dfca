"""`gwc demo` as a user runs it after the README's setup: fresh state, embedded database, one command."""

from __future__ import annotations

import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gwc.config import PROJECT_ROOT


@pytest.fixture
def demo_env() -> Iterator[tuple[Path, dict[str, str]]]:
    """etc/demo.toml on a bus group and port of its own, state in a fresh folder the postgres user can reach."""
    var = Path(tempfile.mkdtemp(prefix="gwc-demo-", dir="/var/tmp"))
    var.chmod(0o755)
    text = (PROJECT_ROOT / "etc" / "demo.toml").read_text()
    rnd = random.Random()
    text = re.sub(r"(?m)^group = .*$", f'group = "239.255.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}"', text)
    text = re.sub(r"(?m)^port = 47110$", f"port = {rnd.randrange(20000, 60000)}", text)
    config = var / "demo.toml"
    config.write_text(text)
    env = {k: v for k, v in os.environ.items() if k not in ("GWC_DATABASE_URL", "GWC_CONFIG")}
    env.update(GWC_VAR=str(var / "state"), PYTHONUNBUFFERED="1")
    try:
        yield config, env
    finally:
        subprocess.run(
            [sys.executable, "-m", "gwc", "stop"],
            env={**env, "GWC_CONFIG": str(config)},
            capture_output=True,
            timeout=120,
        )
        shutil.rmtree(var, ignore_errors=True)


def test_demo_runs_section_7_from_fresh_state_and_exits_0(demo_env: tuple[Path, dict[str, str]]) -> None:
    config, env = demo_env
    t0 = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "gwc", "demo", "--config", str(config)],
        env=env,
        capture_output=True,
        text=True,
        timeout=150,
    )
    took = time.monotonic() - t0
    out = result.stdout
    assert result.returncode == 0, f"exit {result.returncode}\n{out[-6000:]}\n{result.stderr[-2000:]}"
    assert took < 120, f"the demonstration took {took:.0f}s"
    assert "Traceback" not in out + result.stderr
    for told in (
        "alarm 1 HOME_CMM",
        "work order entry",
        "status line: IMPORT",
        "operator: import entity",
        "operator: export entity",
        "start machine wc2 while lots run",
        "stop machine mazak while lots run",
        "results of each lot:",
        "machine run results",
        "RESULT=PASS",
        "trace where --machine wc2: entities",
        "demonstration succeeded",
        "stop: database: stopped",
    ):
        assert told in out, f"the demonstration does not say {told!r}:\n{out[-4000:]}"
    lots = re.findall(r"entity +\d+ (alum_chess_set|milled_pawn) +exported +(PASS|FAIL|SCRAP)", out)
    assert len(lots) == 5, out[-4000:]
    # the production record's genealogy: every entity's runs as its traveller has them (gwc trace entity)
    assert out.count("runs, as the traveller says") == 5, out[-4000:]
    assert not list((Path(env["GWC_VAR"]) / "run").glob("*.pid")), "the demonstration left processes behind"
