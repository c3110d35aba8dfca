"""spawn_process: the environment a process of the cell starts with."""

from __future__ import annotations

import sys
from pathlib import Path

from gwc.cell import Proc, out_file, spawn_process
from gwc.soak.private_config import write_config


def test_a_process_gets_the_cells_environment_and_an_extra_one_overrides_it(tmp_path: Path) -> None:
    # The soak restarts a module with its faults configuration: GWC_CONFIG given again must win, not raise.
    cfg = write_config(tmp_path / "etc" / "cell.toml", {"cell": {"name": "t", "var": str(tmp_path / "var")}})
    show = (sys.executable, "-c", "import os; print(os.environ['GWC_CONFIG'], os.environ['GWC_VAR'])")
    for extra, config in (
        (None, str(cfg.path.resolve())),
        ({"GWC_CONFIG": "/elsewhere/cell.toml"}, "/elsewhere/cell.toml"),
    ):
        proc = Proc("probe", command=show)
        out = out_file(cfg, proc.name)
        out.unlink(missing_ok=True)
        assert spawn_process(cfg, proc, extra).wait(10) == 0
        assert out.read_text().split() == [config, str(cfg.var.resolve())]
