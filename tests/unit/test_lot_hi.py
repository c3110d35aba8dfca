"""The orders-and-lots commands of the Human Interface and the lot-script loader, without a running cell."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from gwc.cli import cli
from gwc.client.orders import order_status, parse_items
from gwc.errors import GwcError
from gwc.lot.errors import LotError
from gwc.lot.run import load_script, resolve_path
from tests.conftest import make_config

MY_COMMANDS = [
    ["order"],
    ["order", "new"],
    ["order", "list"],
    ["order", "show"],
    ["lots"],
    ["import"],
    ["export"],
    ["customer", "add"],
    ["customer", "list"],
    ["product", "list"],
    ["script", "register"],
    ["script", "list"],
    ["demo"],
]


def gwc(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "gwc", *args], env=env, capture_output=True, text=True, timeout=60)


def test_order_items_parse_and_bad_ones_say_how_to_write_them() -> None:
    assert parse_items(("alum_chess_set=2", "milled_pawn", "alum_chess_set=1")) == [
        ("alum_chess_set", 3),
        ("milled_pawn", 1),
    ]
    for bad in ("x=0", "x=-1", "x=two", "=3"):
        with pytest.raises(GwcError, match="PRODUCT=QUANTITY"):
            parse_items((bad,))


def test_an_orders_status_follows_its_entities() -> None:
    assert order_status({}) == "NEW"
    assert order_status({"created": 2}) == "NEW"
    assert order_status({"waiting_import": 1, "created": 1}) == "WAITING IMPORT"
    assert order_status({"running": 1, "exported": 1}) == "RUNNING"
    assert order_status({"exported": 2}) == "DONE"
    assert order_status({"exported": 1, "failed": 1}) == "DONE (with failures)"


def test_shipped_scripts_load_and_broken_ones_are_refused_clearly(tmp_path: Path) -> None:
    for path in ("gwc/lot/scripts/chess.py", "gwc/lot/scripts/mill_and_measure.py"):
        assert callable(load_script(resolve_path(path)).main)
    cases = {
        "missing.py": None,
        "syntax.py": "def main(entity:\n",
        "nomain.py": "x = 1\n",
        "raises.py": "raise RuntimeError('boom')\n",
    }
    for name, text in cases.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(LotError) as e:
            load_script(tmp_path / name)
        assert str(tmp_path / name) in str(e.value)


def test_every_command_says_what_it_does() -> None:
    for cmd in MY_COMMANDS:
        result = CliRunner().invoke(cli, [*cmd, "--help"])
        assert result.exit_code == 0, (cmd, result.output)
        lines = result.output.splitlines()
        assert lines[0].startswith("Usage:") and lines[2].strip(), (cmd, result.stdout)


def test_missing_database_is_one_clear_line(tmp_path: Path) -> None:
    dead = tmp_path / "nosocket"
    dead.mkdir()
    url = f"postgresql://gwc@/gwc?host={dead}&connect_timeout=1"
    cfg = make_config(tmp_path, url)
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=url)
    for args in (("lots",), ("order", "new", "-c", "NJIT", "alum_chess_set=1")):
        result = gwc(env, *args)
        err = result.stderr.strip().splitlines()
        assert result.returncode != 0 and len(err) == 1, (args, result.stderr)
        assert err[0].startswith("gwc: ") and "database" in err[0], err
        assert "Traceback" not in result.stderr + result.stdout


def test_scripts_customers_and_products_are_registered(tmp_path: Path, database_url: str) -> None:
    cfg = make_config(tmp_path, database_url)
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=database_url)
    script = tmp_path / "bracket.py"
    script.write_text("def main(entity):\n    entity.wait_for_import()\n")
    assert gwc(env, "script", "register", "bracket", str(script), "--product", "bracket").returncode == 0
    assert gwc(env, "customer", "add", "ACME", "--name", "Acme Corp").returncode == 0
    listed = gwc(env, "script", "list").stdout
    assert "bracket" in listed and str(script) in listed
    assert "bracket" in gwc(env, "product", "list").stdout
    assert "Acme Corp" in gwc(env, "customer", "list").stdout
    bad = gwc(env, "order", "new", "--customer", "NOBODY", "bracket=1")
    assert bad.returncode != 0 and "unknown customer 'NOBODY'" in bad.stderr
    broken = tmp_path / "broken.py"
    broken.write_text("x = 1\n")
    refused = gwc(env, "script", "register", "broken", str(broken))
    assert refused.returncode != 0 and "has no main(entity)" in refused.stderr
