"""The configuration of a private cell (tests, benchmarks, soaks): a bus group and port of its own, and
keys of its own, written beside the cell it configures (gwc/soak/cell.py) rather than in gwc.config,
which every process imports and which must not depend on the bus's keys."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

from gwc.config import Config, dump_toml, load_config
from gwc.ipc import keys


def write_config(path: Path, doc: dict[str, Any]) -> Config:
    """Write a cell configuration (for tests, benchmarks and private cells), give its cell keys of its
    own if it has none, and load it back. Such a cell runs as whoever starts it (`[cell] user = ""`,
    gwc.hostuser) unless `doc` names its user."""
    doc = {**doc, "cell": {"user": "", **doc.get("cell", {})}}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_toml(doc))
    cfg = load_config(path)
    keys.ensure(cfg.bus)
    return cfg


def private_bus(**settings: Any) -> dict[str, Any]:
    """[bus] settings of a private cell (tests, benchmarks, soaks): a multicast group and port of its
    own, so that it never hears another cell on this machine."""
    rnd = random.SystemRandom()
    return {
        "group": f"239.255.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}",
        "port": rnd.randrange(20000, 60000),
        **settings,
    }
