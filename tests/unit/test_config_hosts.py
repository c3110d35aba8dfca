"""Placement of a cell over several hosts (cell.toml [[host]]): which host this is, what runs here."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from gwc import db
from gwc.agent.unit import systemd_unit
from gwc.cell import cell_procs
from gwc.errors import ConfigError, DatabaseError
from gwc.soak.private_config import write_config

HOSTS = [{"name": "h1", "address": "127.0.0.1"}, {"name": "h2", "address": "198.51.100.7"}]


def placed(tmp_path: Path, **doc: Any) -> Any:
    base: dict[str, Any] = {
        "cell": {"name": "t", "var": str(tmp_path / "var")},
        "host": HOSTS,
        "database": {"host": "h1"},
        "module": [{"name": "ms", "host": "h1"}, {"name": "msched", "host": "h1"}],
        "machine": [{"id": "wc1", "kind": "dummy", "host": "h2"}, {"id": "wc2", "kind": "dummy", "host": "h1"}],
    }
    return write_config(tmp_path / "etc" / "cell.toml", {**base, **doc})


def test_the_host_is_found_from_its_own_address_and_the_bus_uses_that_address(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("GWC_HOST", raising=False)
    cfg = placed(tmp_path, bus={"interface": "10.9.9.9", "ttl": 4})
    assert cfg.host == "h1"  # 127.0.0.1 is local, 198.51.100.7 (TEST-NET-2) is not
    assert (cfg.bus.interface, cfg.bus.ttl) == ("127.0.0.1", 4)


def test_gwc_host_chooses_the_host_and_only_its_modules_and_machines_start_there(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("GWC_HOST", "h2")
    cfg = placed(tmp_path)
    assert cfg.bus.interface == "198.51.100.7"
    assert [p.name for p in cell_procs(cfg)] == ["me:wc1", "wc:wc1"]
    monkeypatch.setenv("GWC_HOST", "h1")
    assert [p.name for p in cell_procs(placed(tmp_path))] == ["ms", "msched", "me:wc2", "wc:wc2"]


def test_the_database_host_runs_the_embedded_cluster_and_the_others_reach_it_by_password(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("GWC_HOST", "h1")
    assert placed(tmp_path).embedded
    monkeypatch.setenv("GWC_HOST", "h2")
    cfg = placed(tmp_path)
    assert not cfg.embedded
    with pytest.raises(DatabaseError, match="copy var/secrets/ from the database host"):
        db.database_url(cfg, "wc")
    (cfg.var / "secrets").mkdir(parents=True, exist_ok=True)  # it holds the cell key already
    (cfg.var / "secrets" / "database").write_text("gwc_wc s3cr/t\ngwc_hi other\n")
    assert db.database_url(cfg, "wc") == "postgresql://gwc_wc:s3cr%2Ft@127.0.0.1:5432/gwc"
    assert db.database_url(cfg).startswith("postgresql://gwc_hi:other@127.0.0.1:5432/gwc")


def test_a_one_host_cell_runs_everything_here(tmp_path: Path) -> None:
    cfg = placed(tmp_path, host=[], module=[{"name": "ms"}], machine=[{"id": "wc1", "kind": "dummy"}])
    assert cfg.host is None
    assert [p.name for p in cell_procs(cfg)] == ["ms", "me:wc1", "wc:wc1"]


@pytest.mark.parametrize(
    ("doc", "env", "message"),
    [
        ({"machine": [{"id": "wc1", "kind": "dummy"}]}, "h1", "machine wc1 must name its host"),
        ({"module": [{"name": "ms", "host": "h9"}]}, "h1", "module ms must name its host, one of h1, h2"),
        ({}, "h7", "GWC_HOST='h7' is not one of the cell's hosts"),
        (
            {
                "host": [{"name": "h1", "address": "198.51.100.1"}, {"name": "h2", "address": "198.51.100.2"}],
                "module": [],
                "machine": [],
            },
            "",
            "cannot tell which of the cell's hosts",
        ),
        ({"bus": {"ttl": 0}}, "h1", "bus.ttl must be 1..255"),
        ({"database": {"host": "h5"}}, "h1", "\\[database\\] host must name the host that runs the embedded"),
        ({"host": [], "module": [{"name": "ms", "host": "h1"}], "machine": []}, "", "has no \\[\\[host\\]\\] tables"),
    ],
)
def test_a_placement_that_cannot_work_is_one_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, doc: dict[str, Any], env: str, message: str
) -> None:
    monkeypatch.setenv("GWC_HOST", env)
    with pytest.raises(ConfigError, match=message):
        placed(tmp_path, **doc)


def test_gwc_agent_prints_a_systemd_unit_for_this_host(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GWC_HOST", "h2")
    unit = systemd_unit(placed(tmp_path))
    assert "Environment=GWC_HOST=h2\n" in unit and "KillMode=process\n" in unit and "Restart=always\n" in unit
    assert f"ExecStart={sys.executable} -m gwc agent\n" in unit
